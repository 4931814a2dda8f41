"""A :class:`RaceEnv` from friendly arguments (a track's name, a scenario, an opponent checkpoint), for the
gymnasium and PettingZoo adapters and for scripts."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from spiral.config.airframe import AirframeCfg, resolve_airframe
from spiral.config.env import EnvCfg
from spiral.config.load import load_track
from spiral.config.sim import SimCfg
from spiral.config.track import TrackSpec
from spiral.core.checkpoint import load_policy
from spiral.core.errors import UsageError
from spiral.core.policy import OpponentPolicy
from spiral.core.scenario import SCENARIO_DRONES
from spiral.core.scenario import learner_slots as team_a_slots
from spiral.env.race_env import RaceEnv
from spiral.env.setting import RaceSetting

__all__ = ["SHIPPED_TRACKS", "Opponent", "OpponentFactory", "RaceOptions", "make_race_env", "resolve_track"]

SHIPPED_TRACKS = Path(__file__).resolve().parents[2] / "tracks"
"""Folder of the tracks that come with spiral; :func:`resolve_track` finds them by name."""

OpponentFactory = Callable[[RaceEnv], OpponentPolicy]
"""Builds an opponent policy for a freshly built env (e.g. a planner that reads the env's state)."""

Opponent = OpponentPolicy | str | Path | None
"""``None`` (opponent slots stay empty), the name of an :data:`OpponentFactory`, a checkpoint path, or a callable
``OpponentPolicy``."""


def resolve_track(track: str | Path | TrackSpec) -> TrackSpec:
    """A ``TrackSpec`` as is, a YAML file, or the name of a shipped track (``oval4``, ``circuit6``, ...)."""
    if isinstance(track, TrackSpec):
        return track
    path = Path(track)
    if not path.is_file() and path.suffix == "" and (SHIPPED_TRACKS / f"{track}.yaml").is_file():
        path = SHIPPED_TRACKS / f"{track}.yaml"
    if not path.is_file():
        known = ", ".join(sorted(p.stem for p in SHIPPED_TRACKS.glob("*.yaml")))
        raise FileNotFoundError(f"track {str(track)!r}: no such file and no shipped track of that name ({known})")
    return load_track(path)


def _model(value: Any, model: type, what: str) -> Any:
    if value is None:
        return model()
    if isinstance(value, model):
        return value
    if isinstance(value, dict):
        return model.model_validate(value)
    raise TypeError(f"{what}: expected a {model.__name__}, a dict or None, got {type(value).__name__}")


def _opponent(opponent: Opponent, named: Mapping[str, OpponentFactory], device: str
              ) -> tuple[OpponentPolicy | None, OpponentFactory | None, dict[str, Any] | None]:
    """The opponent's policy, or the factory that builds it once the env exists, and a checkpoint's env settings."""
    factories = {name.lower(): factory for name, factory in named.items()}
    if isinstance(opponent, str) and opponent.lower() in factories:
        return None, factories[opponent.lower()], None
    if isinstance(opponent, (str, Path)):
        policy = load_policy(Path(opponent), device=device)
        return policy, None, policy.meta["env"]
    if callable(opponent):
        return opponent, None, None
    if opponent is not None:
        names = "".join(f"{name!r}, " for name in named)
        raise TypeError(f"opponent: expected None, {names}a checkpoint path or a callable, got {opponent!r}")
    return None, None, None


@dataclass(frozen=True)
class RaceOptions:
    """What race env to build, in friendly forms: the keyword arguments of ``spiral/Race-v0`` (the gymnasium and
    PettingZoo adapters)."""

    track: str | Path | TrackSpec = "oval4"
    """A ``TrackSpec``, a track YAML file, or the name of a shipped track."""
    scenario: Literal["solo", "1v1", "2v2"] = "solo"
    """Scenario: ``solo`` (1 drone), ``1v1`` (2) or ``2v2`` (4)."""
    opponent: Opponent = None
    """Who flies the opponent slots: ``None`` (absent), the name of a named opponent (any case), a checkpoint path
    (its frozen policy; its env settings are used when ``env_cfg`` is None) or a callable."""
    env_cfg: EnvCfg | dict | None = None
    """Observation, action, reward and episode settings (``EnvCfg`` or a dict of its fields)."""
    sim: SimCfg | dict | None = None
    """Simulator settings (``SimCfg`` or a dict)."""
    airframe: str | AirframeCfg = "cf2x"
    """A built-in airframe's name or an ``AirframeCfg``."""
    learner_slots: Sequence[int] | None = None
    """Slots the caller drives; the scenario's learner team when None (slot 0, or 0 and 1 in 2v2)."""
    device: str = "cpu"
    """``cpu`` or ``cuda:N``."""
    seed: int = 0
    """Seed of the start placements."""
    training: bool = True
    """Training mode: a world resets in ``step`` when its race ends, from training starts (with the start
    cuts of ``env``); False is evaluation mode: every world races once from
    ``episode.eval_starts`` and drones that are done stay frozen."""

    def setting(self) -> RaceSetting:
        """The track, airframe and simulator settings these options name."""
        air = self.airframe if isinstance(self.airframe, AirframeCfg) else resolve_airframe(self.airframe)
        return RaceSetting(resolve_track(self.track), air, _model(self.sim, SimCfg, "sim"))


def make_race_env(options: RaceOptions, *, world_count: int = 1, env_class: type[RaceEnv] = RaceEnv,
                  named_opponents: Mapping[str, OpponentFactory] | None = None) -> RaceEnv:
    """Build the :class:`RaceEnv` of ``options`` with ``world_count`` races stepped together (the gymnasium and
    PettingZoo adapters use it).

    ``env_class`` is ``RaceEnv`` or a subclass; ``named_opponents`` are the opponents ``options.opponent`` may name,
    built for the env (the gymnasium adapter's ``"se-ibr"``).
    """
    o = options
    if o.scenario not in SCENARIO_DRONES:
        raise UsageError(f"scenario: expected one of {', '.join(SCENARIO_DRONES)}, got {o.scenario!r}")
    drones = SCENARIO_DRONES[o.scenario]
    slots = list(o.learner_slots) if o.learner_slots is not None else team_a_slots(o.scenario)
    policy, factory, stored_env = _opponent(o.opponent, named_opponents or {}, o.device)
    env_cfg = stored_env if o.env_cfg is None else o.env_cfg
    if o.opponent is not None and len(slots) == drones:
        raise UsageError(f"opponent: a {o.scenario} race whose every slot is driven by the caller has no opponent slot")
    env = env_class(o.setting(), _model(env_cfg, EnvCfg, "env_cfg"), world_count=world_count,
                    drones_per_world=drones, learner_slots=slots, device=o.device, seed=o.seed, training=o.training)
    policy = factory(env) if factory is not None else policy
    if policy is not None:
        _join_opponent(env, policy)
    return env


def _join_opponent(env: RaceEnv, policy: OpponentPolicy) -> None:
    """Let ``policy`` fly ``env``'s opponent slots from a fresh reset, if it reads the env's observation layout."""
    layout = getattr(policy, "obs_layout", None)
    if layout is not None and layout != env.obs_builder.layout():
        raise UsageError(f"opponent: checkpoint observation layout {layout} differs from the env's "
                         f"{env.obs_builder.layout()} (pass env_cfg=None to use the checkpoint's)")
    env.set_opponent_policy(policy)
    env.reset()  # the opponents join at a reset
