"""Each drone's race since its world's reset, as a race env keeps it: how it ended (finished, crashed, absent), its
finish and lap times, its crash's kind and the sum of each reward term."""

from __future__ import annotations

import torch

from spiral.env.rewards import REWARD_TERMS

__all__ = ["RaceRecords"]


class RaceRecords:
    """The races of ``drone_count`` drones (flat, world-major, as the env's drones) on ``device``."""

    def __init__(self, drone_count: int, device: torch.device) -> None:
        n = drone_count
        self.finished = torch.zeros(n, dtype=torch.bool, device=device)
        """Lap(s) completed without collision."""
        self.crashed = torch.zeros(n, dtype=torch.bool, device=device)
        """Collided since the reset."""
        self.absent = torch.zeros(n, dtype=torch.bool, device=device)
        """Not in the race (an opponent slot with no opponent policy)."""
        self.lap_time = torch.zeros(n, device=device)
        """Race time of the finish [s]; 0 until then."""
        self.lap_start = torch.zeros(n, device=device)
        """Race time at which each drone's current lap began (its start or its last lap's end) [s]."""
        self.crash_kind = torch.zeros(n, dtype=torch.int32, device=device)
        """The collision kinds of the crash (bits of :data:`~spiral.sim.COLLISION_KINDS`); 0 without one."""
        self.term_sums = {name: torch.zeros(n, device=device) for name in REWARD_TERMS}
        """Each reward term's sum over the race so far (weighted)."""

    def racing(self) -> torch.Tensor:
        """Whether each drone is still in its race: neither crashed, finished nor absent (N,)."""
        return ~(self.crashed | self.finished | self.absent)

    def restart(self, drones: torch.Tensor, absent: torch.Tensor) -> None:
        """Start the races of the drones in the bool mask ``drones`` afresh, those of them in ``absent`` out of it."""
        for buf in (self.lap_time, self.lap_start, self.crash_kind, *self.term_sums.values()):
            buf.masked_fill_(drones, 0)
        self.finished &= ~drones
        self.crashed &= ~drones
        self.absent.copy_(torch.where(drones, absent, self.absent))

    def end(self, crashed_now: torch.Tensor, kind: torch.Tensor, finished_now: torch.Tensor,
            finish_time: torch.Tensor) -> None:
        """End the races of the drones that crashed in this step (``crashed_now``, with the collision ``kind``) and
        of those that finished (``finished_now``, at race time ``finish_time``)."""
        self.crashed |= crashed_now
        self.crash_kind = torch.where(crashed_now, kind, self.crash_kind)
        self.finished |= finished_now
        self.lap_time = torch.where(finished_now, finish_time, self.lap_time)
