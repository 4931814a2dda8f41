"""Where and with what races are flown: the track (or tracks), the airframe and the simulator settings, which travel
together."""

from __future__ import annotations

from dataclasses import dataclass, replace

from spiral.config.airframe import AirframeCfg
from spiral.config.sim import SimCfg
from spiral.config.track import TrackSpec

__all__ = ["RaceSetting"]


@dataclass(frozen=True)
class RaceSetting:
    """The track, the airframe and the simulator settings of a batch of races: what a :class:`~spiral.sim.World`
    simulates (a race env's other settings are its :class:`~spiral.config.env.EnvCfg`)."""

    track: TrackSpec
    airframe: AirframeCfg
    sim: SimCfg
    sim_threads: int = 1
    """CPU threads that step the simulator, each a share of the worlds: how the races are computed, not what they
    are (worlds never interact, so the result is the same for any count; :class:`~spiral.sim.World`)."""
    more_tracks: tuple[TrackSpec, ...] = ()
    """Further tracks the worlds race, a track per world: in training a world draws one of :attr:`tracks` uniformly
    at every reset, in evaluation world w races track (w + k) mod T, k drawn per race; none: every world races
    ``track``."""

    def with_laps(self, laps: int) -> RaceSetting:
        """This setting with races of ``laps`` laps on every track."""
        return replace(self, track=self.track.with_laps(laps),
                       more_tracks=tuple(t.with_laps(laps) for t in self.more_tracks))

    @property
    def tracks(self) -> tuple[TrackSpec, ...]:
        """Every track the worlds race: ``track`` first, then :attr:`more_tracks`."""
        return (self.track, *self.more_tracks)
