"""Where one PPO iteration's time goes, and how far the update is from the CPU's matmul rate.

The rollout is split by the phases of the environment's step (apply action, simulate, race events, rewards, episode
ends, reset, observe; summed over the parts of a stage that mixes scenarios), the opponents' policies in multi-drone
stages (apart from the phase that calls them) and the policy's part (acting, storing the transition, returns). The
update is split from a ``torch.profiler`` trace of rsl-rl's ``PPO.update`` into forward (losses included), backward,
gradient clipping, optimizer step and the observation normaliser. Its samples per second are set against the
*matmul limit*: the rate at which the same update would run if it did nothing but the plain matrix products of its
linear layers (forward, gradient of the input, gradient of the weights) at the speed this CPU reaches on them, timed
here.

On a CUDA device every clock is read after waiting for the device (:func:`device_clock`), so a time is that of the
work queued before it, not of its launch; on a CPU the clocks are plain ``time.perf_counter``.
"""

from __future__ import annotations

import contextlib
import functools
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch
from torch import nn

from spiral.config.stage import StageSpec
from spiral.core.errors import UsageError
from spiral.core.policy import OpponentPolicy
from spiral.env import race_env
from spiral.env.mixed import MixedRaceEnv
from spiral.env.setting import RaceSetting
from spiral.train.runner import StageStart, StageTrainer

__all__ = ["ENV_PHASES", "device_clock", "linear_layers", "matmul_seconds", "profile_iteration", "timed_methods",
           "update_flops_per_sample"]

ENV_PHASES = ("apply_actions", "simulate", "race_events", "step_rewards", "episode_ends", "reset_ended",
              "get_observations")
"""The phases of ``RaceEnv.step``, in its order: functions of :mod:`spiral.env.race_env`, and the env's
``get_observations``."""


def device_clock(device: str | torch.device) -> Callable[[], float]:
    """A wall clock [s] for timing work on ``device``: ``time.perf_counter`` itself on a CPU; on a CUDA device a
    clock that first waits for the device (``torch.cuda.synchronize``: every stream of it, Warp's as well as
    torch's), so that a time read after queued work includes that work."""
    device = torch.device(device)
    if device.type != "cuda":
        return time.perf_counter

    def now() -> float:
        torch.cuda.synchronize(device)
        return time.perf_counter()

    return now


def linear_layers(*modules: nn.Module) -> list[tuple[int, int]]:
    """(inputs, outputs) of every ``nn.Linear`` in ``modules``, in order."""
    return [(m.in_features, m.out_features) for mod in modules for m in mod.modules() if isinstance(m, nn.Linear)]


def _first_layers(*modules: nn.Module) -> set[int]:
    """Indices (into :func:`linear_layers`) of each module's first linear layer, whose input needs no gradient."""
    first, i = set(), 0
    for mod in modules:
        first.add(i)
        i += sum(isinstance(m, nn.Linear) for m in mod.modules())
    return first


def update_flops_per_sample(layers: list[tuple[int, int]], first: set[int]) -> int:
    """Multiply-add FLOPs (2 per multiply-add) one sample costs in one epoch of the update: forward, gradient of
    the weights and, except for a network's first layer, gradient of the input."""
    return sum(2 * n_in * n_out * (2 if i in first else 3) for i, (n_in, n_out) in enumerate(layers))


def matmul_seconds(layers: list[tuple[int, int]], first: set[int], batch: int, *, repeats: int = 20,
                   device: str = "cpu", dtype: torch.dtype = torch.float32) -> tuple[float, float]:
    """Wall and processor seconds (best of ``repeats`` each) one mini-batch of ``batch`` samples spends in plain
    matrix products of ``layers`` on ``device`` in ``dtype``: x·Wᵀ forward, gᵀ·x for the weights and g·W for the
    input where it is needed."""
    mats = []
    for i, (n_in, n_out) in enumerate(layers):
        x, w, g = (torch.randn(*shape, device=device, dtype=dtype)
                   for shape in ((batch, n_in), (n_out, n_in), (batch, n_out)))
        mats.append((x, w, g, i not in first))
    clock = device_clock(device)

    def once() -> None:
        for x, w, g, grad_input in mats:
            torch.mm(x, w.t())
            torch.mm(g.t(), x)
            if grad_input:
                torch.mm(g, w)

    once()
    wall = cpu = float("inf")
    for _ in range(repeats):
        t0, c0 = clock(), time.process_time()
        once()
        wall, cpu = min(wall, clock() - t0), min(cpu, time.process_time() - c0)
    return wall, cpu


@contextlib.contextmanager
def timed_methods(obj: Any, names: tuple[str, ...], totals: dict[str, float], *,
                  clock: Callable[[], float] = time.perf_counter) -> Iterator[None]:
    """Accumulate the wall time of ``obj``'s methods ``names`` into ``totals`` while the context is open (``obj`` an
    instance, a class to time the methods of all its instances, or a module to time its functions), read off
    ``clock`` (a :func:`device_clock` for methods that queue work on a GPU)."""
    def wrap(name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        def timed(*args: Any, **kwargs: Any) -> Any:
            t0 = clock()
            try:
                return fn(*args, **kwargs)
            finally:
                totals[name] += clock() - t0
        return timed

    own = {name: vars(obj)[name] for name in names if name in vars(obj)}  # a class's own methods: put back after
    for name in names:
        setattr(obj, name, wrap(name, getattr(obj, name)))
    try:
        yield
    finally:
        for name in names:
            if name in own:
                setattr(obj, name, own[name])
            else:
                delattr(obj, name)


def _rollout(trainer: StageTrainer, obs: Any, totals: dict[str, float],
             opponents: dict[str, OpponentPolicy]) -> Any:
    """One rollout of :meth:`StageTrainer.collect`, with the policy's and the env's parts timed (the step's phases,
    summed over the parts of a mixed env, and the opponents' policies apart from the ``apply_actions`` phase that
    calls them)."""
    parts = trainer.env.parts.values() if isinstance(trainer.env, MixedRaceEnv) else [trainer.env]
    timed = functools.partial(timed_methods, clock=device_clock(trainer.device))
    with contextlib.ExitStack() as stack:
        stack.enter_context(timed(trainer.runner.alg, ("act", "process_env_step", "compute_returns"), totals))
        stack.enter_context(timed(race_env, ENV_PHASES[:-1], totals))  # every part's: step looks them up there
        for env in parts:
            stack.enter_context(timed(env, ENV_PHASES[-1:], totals))
        inside: dict[str, float] = defaultdict(float)
        for kind in {type(policy) for policy in opponents.values()}:  # a call looks __call__ up on the class
            stack.enter_context(timed(kind, ("__call__",), inside))
        obs = trainer.collect(obs)[0]
    if inside:
        totals["opponents"] += inside["__call__"]
        totals["apply_actions"] -= inside["__call__"]
    return obs


def _update_parts(trace: torch.profiler.profile, *, on_device: bool = False) -> dict[str, float]:
    """Seconds of the update's top-level profiler events by part: their processor time, or with ``on_device`` the
    time of the GPU kernels they (and the events under them) launched (their processor time all the same if the
    trace holds no kernel times, as without CUDA's profiling library)."""
    on_device = on_device and any(ev.device_time_total for ev in trace.events())
    parts: dict[str, float] = defaultdict(float)
    for ev in trace.events():
        if ev.cpu_parent is not None:
            continue
        name = ev.name
        if name.startswith("autograd::engine"):
            part = "backward"
        elif name.startswith("Optimizer.step"):
            part = "optimizer"
        elif name.startswith("Optimizer.zero_grad"):
            part = "zero_grad"
        elif name in ("clip_grad_norm", "update_normalization"):
            part = name
        else:
            part = "forward"
        parts[part] += (ev.device_time_total if on_device else ev.cpu_time_total) * 1e-6
    return dict(parts)


def _traced_update(alg: Any, *, on_device: bool = False) -> torch.profiler.profile:
    """rsl-rl's update under the profiler, with gradient clipping and the normaliser labelled; with ``on_device``
    the GPU's kernels traced too."""
    record = torch.profiler.record_function
    clip, actor_norm, critic_norm = nn.utils.clip_grad_norm_, alg.actor.update_normalization, \
        alg.critic.update_normalization

    def labelled(label: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        def call(*args: Any, **kwargs: Any) -> Any:
            with record(label):
                return fn(*args, **kwargs)
        return call

    nn.utils.clip_grad_norm_ = labelled("clip_grad_norm", clip)
    alg.actor.update_normalization = labelled("update_normalization", actor_norm)
    alg.critic.update_normalization = labelled("update_normalization", critic_norm)
    try:
        activity = torch.profiler.ProfilerActivity
        with torch.profiler.profile(activities=[activity.CPU, *([activity.CUDA] if on_device else [])]) as trace:
            alg.update()
    finally:
        nn.utils.clip_grad_norm_ = clip
        del alg.actor.update_normalization, alg.critic.update_normalization
    return trace


def profile_iteration(setting: RaceSetting, stage: StageSpec, *, iterations: int = 3, device: str = "cpu",
                      seed: int = 0, start: StageStart | None = None) -> dict[str, Any]:
    """Profile ``iterations`` PPO iterations of ``stage`` after one warm-up iteration (times are per iteration).

    A multi-drone stage needs ``start``: the checkpoint it starts from and the opponents it races.
    """
    start = start or StageStart()
    opponents = start.opponents
    if stage.scenario != "solo" and not opponents:
        raise UsageError(f"stage {stage.name!r}: profiling a {stage.scenario} stage needs the checkpoint it starts "
                         "from and its opponents")
    with tempfile.TemporaryDirectory() as tmp:
        trainer = StageTrainer(setting, stage, Path(tmp), start=start, device=device, seed=seed, progress=False,
                               log=lambda _: None)
        alg = trainer.runner.alg
        alg.train_mode()
        obs = trainer.vec_env.get_observations().to(device)
        obs = _rollout(trainer, obs, defaultdict(float), opponents)
        alg.update()
        obs, timings = _timed_iterations(trainer, obs, opponents, iterations)
        obs = _rollout(trainer, obs, defaultdict(float), opponents)
        on_device = torch.device(device).type == "cuda"  # the GPU's share of each part, not its launches'
        parts = _update_parts(_traced_update(alg, on_device=on_device), on_device=on_device)
    return _report(stage, trainer, device, timings, parts)


@dataclass
class _Timings:
    """Seconds the profiled iterations took, summed over them."""

    iterations: int
    rollout_parts: dict[str, float] = field(default_factory=lambda: defaultdict(float))
    """The rollouts' wall time by part."""
    rollout_s: float = 0.0
    """The rollouts' wall time."""
    update_s: float = 0.0
    """The updates' wall time."""
    update_cpu_s: float = 0.0
    """The updates' processor time."""


def _timed_iterations(trainer: StageTrainer, obs: Any, opponents: dict[str, OpponentPolicy],
                      iterations: int) -> tuple[Any, _Timings]:
    """Run ``iterations`` PPO iterations from ``obs``, timing the rollouts by part and the updates; the observations
    after them and the times."""
    alg, t, clock = trainer.runner.alg, _Timings(iterations), device_clock(trainer.device)
    for _ in range(iterations):
        t0 = clock()
        obs = _rollout(trainer, obs, t.rollout_parts, opponents)
        t.rollout_s += clock() - t0
        t0, c0 = clock(), time.process_time()
        alg.update()
        t.update_s, t.update_cpu_s = t.update_s + clock() - t0, t.update_cpu_s + time.process_time() - c0
    return obs, t


def _report(stage: StageSpec, trainer: StageTrainer, device: str, t: _Timings,
            parts: dict[str, float]) -> dict[str, Any]:
    """The profile's numbers: the stage's sizes, the rollout's and the update's times per iteration (the update's
    parts as shares of the traced one, ``parts``), and the update against the matmul limit."""
    alg, iterations = trainer.runner.alg, t.iterations
    ppo, samples = stage.ppo, stage.ppo.num_steps_per_env * trainer.env.num_envs
    layers, first = linear_layers(alg.actor, alg.critic), _first_layers(alg.actor, alg.critic)
    mini_batch, passes = samples // ppo.num_mini_batches, ppo.num_mini_batches * ppo.num_learning_epochs
    dtype = torch.bfloat16 if ppo.mixed_precision else torch.float32  # the precision of the update's products
    mm_s, mm_cpu_s = (x * passes for x in matmul_seconds(layers, first, mini_batch, device=device, dtype=dtype))
    flops = update_flops_per_sample(layers, first) * samples * ppo.num_learning_epochs
    update_s, update_cpu_s = t.update_s / iterations, t.update_cpu_s / iterations
    traced = sum(parts.values())
    return {
        "stage": stage.name, "device": device, "torch_threads": torch.get_num_threads(), "worlds": stage.worlds,
        "learner_drones": trainer.env.num_envs,
        "obs_dim": trainer.env.obs_dim, "samples_per_iteration": samples, "mini_batch": mini_batch,
        "epochs": ppo.num_learning_epochs, "layers": layers, "update_flops": flops, "matmul_dtype": str(dtype),
        "rollout_s": t.rollout_s / iterations,
        "rollout_parts_s": {k: v / iterations for k, v in t.rollout_parts.items()},
        "update_s": update_s, "update_cpu_s": update_cpu_s,
        "update_parts_share": {k: v / traced for k, v in parts.items()},
        "update_samples_per_s": samples / update_s, "update_samples_per_cpu_s": samples / update_cpu_s,
        "matmul_s": mm_s, "matmul_cpu_s": mm_cpu_s, "matmul_gflops": flops / mm_s * 1e-9,
        "matmul_limit_samples_per_s": samples / mm_s,
        "update_over_matmul_limit": update_s / mm_s, "update_over_matmul_limit_cpu": update_cpu_s / mm_cpu_s,
    }
