"""Racing metrics over the drones' gate passages: overtakes, lead changes, who won from behind, time per lap,
contacts per lap. Pure functions of :class:`~spiral.env.racing.RaceResults`; docs/evaluation.md defines each.

A drone's passages are numbered in passing order: passage 0 is the first gate it flies through, passage ``k`` the
``k``-th after it, and a race of ``L`` laps of ``G`` gates ends at passage ``L·G`` (the first gate again). From the
start box every drone's passage ``k`` is the same gate; started along the track, a drone's passage ``k`` is ``k``
passages into its race, so comparing two drones at passage ``k`` compares how far each has come.
"""

from __future__ import annotations

from typing import Any

import torch

from spiral.core.outcome import race_winner
from spiral.env.racing import RaceResults
from spiral.sim import COLLISION_KINDS

__all__ = ["lap_times", "lead_changes", "order_changes", "passage_leaders", "racecraft", "won_from_behind"]


def _passed(split_time: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
    """Which drones made each passage (W, D, P): a race time above 0, in a slot that raced."""
    return (split_time > 0) & present[..., None]


def order_changes(split_time: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
    """Overtakes per race (W,): for every pair of drones, the times their order changes from one passage to the next.

    Two drones are ordered at passage ``k`` when both made it, by who made it first; at equal times they are not
    ordered, and a pair's order is compared with the last passage at which it was ordered, so ``ahead, level, ahead``
    counts no change and ``ahead, level, behind`` one. A drone that crashed makes no more passages, so it drops out
    of the order without counting as overtaken.

    Args:
        split_time: Race time of each drone's passages (W, D, P), 0 where not made [s].
        present: Slots that raced (W, D).
    """
    made = _passed(split_time, present)
    both = made[:, :, None, :] & made[:, None, :, :]
    sign = torch.sign(split_time[:, :, None, :] - split_time[:, None, :, :]) * both  # (W, D, D, P)
    last = torch.zeros_like(sign[..., 0])
    changes = torch.zeros_like(last)
    for k in range(sign.shape[-1]):
        now = sign[..., k]
        changes += (now != 0) & (last != 0) & (now != last)
        last = torch.where(now != 0, now, last)
    return changes.triu(diagonal=1).sum(dim=(1, 2)).long()


def passage_leaders(split_time: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
    """The drone first through each passage (W, P): the slot that made it earliest, −1 where nobody made it or two
    drones made it at the same time first."""
    made = _passed(split_time, present)
    times = torch.where(made, split_time, torch.inf)
    first = times.min(dim=1)
    tied = (times == first.values[:, None, :]).sum(dim=1) > 1
    return torch.where(made.any(dim=1) & ~tied, first.indices, -1)


def lead_changes(split_time: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
    """Lead changes per race (W,): passages whose leader (:func:`passage_leaders`) differs from the last passage's that
    had one."""
    leaders = passage_leaders(split_time, present)
    last = torch.full_like(leaders[:, 0], -1)
    changes = torch.zeros_like(last)
    for k in range(leaders.shape[1]):
        now = leaders[:, k]
        changes += (now >= 0) & (last >= 0) & (now != last)
        last = torch.where(now >= 0, now, last)
    return changes


def won_from_behind(res: RaceResults, team: torch.Tensor) -> torch.Tensor:
    """Per race (W,): 1 when the race's winning team was not the team first through the first gate, 0 when it was,
    −1 without a winner or without a team first there; both by :func:`~spiral.core.outcome.race_winner`, the winner
    from the drones' finish times, the leader from their first passages (``team``: each slot's team, (D,))."""
    assert res.split_time is not None
    teams = [(team == t).nonzero().flatten().tolist() for t in range(int(team.max()) + 1)]
    winner = race_winner(res.finished & res.present, res.lap_time, teams)
    first = res.split_time[..., 0]
    leader = race_winner(_passed(res.split_time, res.present)[..., 0], first, teams)
    return torch.where((winner >= 0) & (leader >= 0), (winner != leader).long(), -1)


def lap_times(split_time: torch.Tensor, laps: int) -> torch.Tensor:
    """Time of each lap (W, D, laps), 0 where the drone did not complete it [s]: lap 1 from the race's start to the
    end of the first lap (``G`` passages after passage 0), each later lap between consecutive lap ends."""
    gates = (split_time.shape[-1] - 1) // laps
    if gates * laps + 1 != split_time.shape[-1]:
        raise ValueError(f"split_time holds {split_time.shape[-1]} passages, not laps × gates + 1 for {laps} laps")
    ends = split_time[..., gates::gates]  # (W, D, laps)
    starts = torch.cat([torch.zeros_like(ends[..., :1]), ends[..., :-1]], dim=-1)
    done = ends > 0
    return torch.where(done, ends - starts, 0.0)


def _mean(x: torch.Tensor) -> float | None:
    return float(x.double().mean()) if x.numel() else None


def racecraft(res: RaceResults, mask: torch.Tensor) -> dict[str, Any]:
    """The racing metrics of the races in which a ``mask`` drone raced (W, D), for ``summarize_races``'s JSON.

    ``overtakes_per_race`` and ``lead_changes_per_race`` count every drone of those races; ``won_from_behind`` is the
    share of the races with a winner and a first-gate leader that a team other than the leader's won; lap times
    (``first_lap``, from the start, and ``flying_lap``, every later lap) and ``drone_contacts_per_lap`` (drone–drone
    crashes of the ``mask`` drones per lap they flew, counting a part lap as its share of the gates) are the ``mask``
    drones'.
    """
    assert res.split_time is not None
    raced = mask.any(dim=1)
    split, present = res.split_time[raced], res.present[raced]
    team = res.team if res.team is not None else torch.arange(res.present.shape[1])
    behind = won_from_behind(res, team)[raced]
    laps = lap_times(res.split_time, res.laps)
    first, flying = laps[..., 0][mask], laps[..., 1:][mask]
    gates = (res.split_time.shape[-1] - 1) // res.laps
    flown = float(_passed(res.split_time, res.present)[mask].sum()) / gates
    contacts = int(((res.crash_kind[mask] & COLLISION_KINDS["drone"]) != 0).sum())
    return {
        "laps": res.laps,
        "overtakes_per_race": _mean(order_changes(split, present)),
        "lead_changes_per_race": _mean(lead_changes(split, present)),
        "won_from_behind": _mean(behind[behind >= 0]),
        "first_lap": _mean(first[first > 0]),
        "flying_lap": _mean(flying[flying > 0]),
        "drone_contacts_per_lap": contacts / flown if flown > 0 else None,
    }
