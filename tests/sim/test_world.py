"""World: batching invariants, determinism, partial resets, exact clocks and non-finite containment."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from pydantic import ValidationError

from spiral.config import SimCfg
from spiral.sim import World
from tests.sim.helpers import ON_CUDA

STATE = ("pos", "vel", "quat", "omega", "rpm")
RACE = ("next_gate", "gates_passed", "out", "crash_time", "pass_time", "step_collision", "world_substeps")


def snapshot(world) -> dict[str, np.ndarray]:
    """Copies of every state, race and controller array of ``world``."""
    out = {k: getattr(world.state, k).numpy().copy() for k in STATE}
    out.update({k: getattr(world.race, k).numpy().copy() for k in RACE})
    out["integral"] = world.integral.numpy().copy()
    return out


def starts(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Random start positions in open air of the gate track and random yaws."""
    return rng.uniform([-3.0, -3.0, 0.8], [-1.0, 3.0, 2.5], (n, 3)), rng.uniform(-3, 3, n)


def test_identical_worlds_stay_identical(make_world, run, targets):
    """Keep four worlds given the same starts and commands equal within 1e-6 over 2 s."""
    world = make_world(world_count=4, drones=2)
    rng = np.random.default_rng(1)
    pos, yaw = starts(rng, 2)
    world.reset_all(np.tile(pos, (4, 1)), np.tile(yaw, 4))
    out = run(world, np.tile(targets(rng, 96, 2), (1, 4, 1)))
    for k in STATE:
        per_world = out[k].reshape(96, 4, 2, -1)
        np.testing.assert_allclose(per_world, np.broadcast_to(per_world[:, :1], per_world.shape), atol=1e-6, rtol=0)
    assert np.abs(out["pos"][-1] - out["pos"][0]).max() > 0.1  # they did move


@pytest.mark.bitwise
def test_trajectory_does_not_depend_on_world_count(make_world, run, targets):
    """Give world 0 the same trajectory, bit for bit, whether it runs alone or beside two other worlds."""
    rng = np.random.default_rng(2)
    pos, yaw = starts(rng, 6)
    cmds = targets(rng, 96, 6)
    alone, crowd = make_world(world_count=1, drones=2), make_world(world_count=3, drones=2)
    alone.reset_all(pos[:2], yaw[:2])
    crowd.reset_all(pos, yaw)
    a, c = run(alone, cmds[:, :2]), run(crowd, cmds)
    for k in STATE:
        np.testing.assert_array_equal(a[k], c[k][:, :2])


@pytest.mark.bitwise
def test_same_seed_gives_bit_identical_runs(make_world, run, targets):
    """Reproduce every state and race array bit for bit from the same seed (on one device)."""
    results = []
    for _ in range(2):
        rng = np.random.default_rng(7)
        world = make_world(world_count=3, drones=4, freeze_crashed=False)
        world.reset_all(*starts(rng, 12))
        run(world, targets(rng, 60, 12, lo=(-3.5, -3.5, 0.2), hi=(3.5, 5.5, 3.5)))
        results.append(snapshot(world))
    for k in results[0]:
        np.testing.assert_array_equal(results[0][k], results[1][k], err_msg=k)
    assert results[0]["out"].any() or results[0]["gates_passed"].any()  # the run had events to reproduce


@pytest.mark.bitwise
def test_reset_of_a_subset_leaves_other_worlds_untouched(make_world, run, targets):
    """Reset world 1 only: worlds 0 and 2 keep every array bit for bit; world 1 restarts like a fresh world."""
    rng = np.random.default_rng(4)
    world = make_world(world_count=3, drones=2)
    world.reset_all(*starts(rng, 6))
    cmds = targets(rng, 40, 6)
    run(world, cmds[:20])
    before = snapshot(world)
    new_pos, new_yaw = starts(rng, 6)
    mask = np.array([0, 1, 0], np.int32)
    dev = world.device
    world.reset(wp.array(mask, dtype=wp.int32, device=dev),
                wp.array(new_pos.astype(np.float32), dtype=wp.vec3, device=dev),
                wp.array(new_yaw.astype(np.float32), dtype=wp.float32, device=dev))
    after = snapshot(world)
    keep = np.array([0, 1, 4, 5])
    for k in (*STATE, "integral", "next_gate", "gates_passed", "out"):
        np.testing.assert_array_equal(after[k][keep], before[k][keep], err_msg=k)
    assert after["world_substeps"].tolist() == [100, 0, 100]
    np.testing.assert_allclose(after["pos"][2:4], new_pos[2:4].astype(np.float32))
    np.testing.assert_array_equal(after["vel"][2:4], 0.0)
    np.testing.assert_array_equal(after["integral"][2:4], 0.0)
    # world 1 now evolves exactly as a fresh world started from the same state
    fresh = make_world(world_count=1, drones=2)
    fresh.reset_all(new_pos[2:4], new_yaw[2:4])
    a, b = run(world, cmds[20:]), run(fresh, cmds[20:, 2:4])
    for k in STATE:
        np.testing.assert_array_equal(a[k][:, 2:4], b[k])


@pytest.mark.bitwise
@pytest.mark.parametrize(("field", "bad"), [("vel", np.nan), ("vel", np.inf), ("omega", -np.inf), ("omega", np.nan)])
def test_nonfinite_state_is_flagged_and_contained(make_world, run, targets, field, bad):
    """Flag only the world whose drone got a NaN or infinite velocity or body rate, keep its stored pose finite,
    leave other drones as before."""
    rng = np.random.default_rng(9)
    pos, yaw = starts(rng, 6)
    cmds = targets(rng, 30, 6)
    clean, hurt = make_world(world_count=3, drones=2), make_world(world_count=3, drones=2)
    for w in (clean, hurt):
        w.reset_all(pos, yaw)
        run(w, cmds[:10])
    state = getattr(hurt.state, field)
    values = state.numpy().copy()
    values[2] = [bad, 0.0, 0.0]  # drone 0 of world 1
    state.assign(values)
    frozen_pos = hurt.state.pos.numpy()[2].copy()
    a, b = run(clean, cmds[10:]), run(hurt, cmds[10:])
    assert hurt.race.world_nonfinite.numpy().tolist() == [0, 1, 0]
    assert clean.race.world_nonfinite.numpy().tolist() == [0, 0, 0]
    for k in sorted({"pos", "quat", "omega", "rpm", "rpy"} - {field}):  # the injected value itself is never overwritten
        assert np.isfinite(b[k]).all(), k
    np.testing.assert_allclose(b["pos"][:, 2], np.broadcast_to(frozen_pos, (20, 3)), rtol=1e-6, atol=1e-9)
    others = [0, 1, 3, 4, 5]
    for k in STATE:
        np.testing.assert_array_equal(a[k][:, others], b[k][:, others], err_msg=k)  # same inputs, same host


def test_world_time_is_exact_at_48_hz(make_world):
    """Take exactly 5 physics substeps per control step at 240/48 Hz, so 48 steps are 1 s; reject 50 Hz."""
    world = make_world(world_count=2)
    world.reset_all(np.array([[-2.0, 1.0, 1.0], [-2.0, 2.0, 1.0]]))
    world.cmd.assign(np.float32([[-2.0, 1.0, 1.0, 0.0], [-2.0, 2.0, 1.0, 0.0]]))
    for _ in range(48):
        world.step()
    assert world.sim.substeps == 5
    assert world.race.world_substeps.numpy().tolist() == [240, 240]
    assert world.world_time().tolist() == pytest.approx([1.0, 1.0], abs=1e-12)
    with pytest.raises(ValidationError, match="ctrl_hz"):
        SimCfg(physics_hz=240, ctrl_hz=50)


def _flight_through_gate_0(rng, targets, drones: int, steps: int):
    """Random starts and targets for ``drones`` drones over ``steps`` control steps, drone 0 flying through gate 0."""
    pos, yaw = starts(rng, drones)
    commands = targets(rng, steps, drones)
    pos[0], yaw[0], commands[:, 0] = (-1.0, 0.0, 1.5), 0.0, (1.5, 0.0, 1.5, 0.0)
    return pos, yaw, commands


def _fly(world, commands, *, nan_at: tuple[int, int] | None = None) -> dict:
    """Step ``world`` through ``commands``; ``nan_at = (step, drone)`` gives that drone a NaN velocity at that step.
    The end state with the attitudes and the per-world health flags."""
    for i, cmd in enumerate(commands):
        wp.copy(world.cmd, wp.array(cmd, dtype=wp.vec4, device=world.device))
        if nan_at is not None and i == nan_at[0]:
            vel = world.state.vel.numpy().copy()
            vel[nan_at[1]] = [np.nan, 0.0, 0.0]
            world.state.vel.assign(vel)
        world.step()
    return snapshot(world) | {"rpy": world.rpy.numpy().copy(), "nonfinite": world.race.world_nonfinite.numpy().copy()}


@pytest.mark.parametrize("sim_device", ["cpu"])  # a GPU replays a CUDA graph instead (the test below)
@pytest.mark.parametrize("downwash", [False, True], ids=["plain", "downwash"])
@pytest.mark.bitwise
def test_replayed_launches_give_exactly_the_plain_launch_path(make_world, targets, downwash):
    """Four drones per world flying random targets (some crash, some fly on, one passes a gate): replaying the
    recorded launches gives bit for bit the state of launching every kernel afresh."""
    pos, yaw, commands = _flight_through_gate_0(np.random.default_rng(7), targets, 16, 120)
    out = {}
    for replay in (False, True):
        world = make_world(world_count=4, drones=4, downwash=downwash)
        world.replay_launches = replay
        world.reset_all(pos, yaw)
        out[replay] = _fly(world, commands)
    assert out[True]["out"].any() and (out[True]["out"] == 0).any() and out[True]["gates_passed"][0] == 1
    for key, value in out[False].items():
        np.testing.assert_array_equal(out[True][key], value, err_msg=key)


@pytest.mark.parametrize("sim_device", ["cpu"])  # CPU threads; a GPU steps every world in one launch
@pytest.mark.parametrize(("world_count", "drones", "threads"), [(5, 4, 2), (5, 4, 3), (7, 1, 2)],
                         ids=["4-drones-2-threads", "4-drones-3-threads", "1-drone-2-threads"])
@pytest.mark.bitwise
def test_worlds_stepped_in_threads_give_exactly_the_one_thread_state(make_world, targets, world_count, drones,
                                                                     threads):
    """Worlds split into uneven contiguous shares, each stepped on its own thread (downwash on, some drones crash,
    one passes a gate, one world's drone goes non-finite): every state, race, controller and attitude array is bit
    for bit that of one thread, and so are the per-world clocks and health flags."""
    n = world_count * drones
    pos, yaw, commands = _flight_through_gate_0(np.random.default_rng(11), targets, n, 60)
    out = {}
    for count in (1, threads):
        world = make_world(world_count=world_count, drones=drones, downwash=True, cpu_threads=count)
        world.reset_all(pos, yaw)
        out[count] = _fly(world, commands, nan_at=(30, n - 1))  # the last world's last drone, half-way
    assert out[1]["out"].any() and (out[1]["out"] == 0).any() and out[1]["gates_passed"][0] == 1
    assert out[1]["nonfinite"].tolist() == [0] * (world_count - 1) + [1]
    for key, value in out[1].items():
        np.testing.assert_array_equal(out[threads][key], value, err_msg=key)


@pytest.mark.parametrize("sim_device", [ON_CUDA])
@pytest.mark.parametrize("downwash", [False, True], ids=["plain", "downwash"])
@pytest.mark.bitwise
def test_cuda_graph_gives_exactly_the_plain_launch_path(make_world, targets, downwash):
    """On a GPU, 300 control steps replayed from the captured CUDA graph give bit for bit the state of launching
    every kernel afresh: drones flying random targets (some crash, some fly on, one passes a gate, one world's drone
    goes non-finite), every state, race, controller and attitude array, the clocks and health flags included."""
    pos, yaw, commands = _flight_through_gate_0(np.random.default_rng(13), targets, 16, 300)
    out = {}
    for graph in (False, True):
        world = make_world(world_count=4, drones=4, downwash=downwash)
        world.use_graph, world.replay_launches = graph, False
        world.reset_all(pos, yaw)
        out[graph] = _fly(world, commands, nan_at=(20, 15))  # the last world's last drone, while it still flies
    assert world._graph is not None and world.device == "cuda:0"  # the second run did replay a graph
    assert out[True]["out"].any() and (out[True]["out"] == 0).any() and out[True]["gates_passed"][0] == 1
    assert out[True]["nonfinite"].tolist() == [0, 0, 0, 1]
    for key, value in out[False].items():
        np.testing.assert_array_equal(out[True][key], value, err_msg=key)


def test_cpu_threads_must_be_positive(make_world):
    """A thread count below one is refused by name."""
    with pytest.raises(ValueError, match="cpu_threads"):
        make_world(cpu_threads=0)


def _fly_the_gates(world: World, starts: np.ndarray, steps: int) -> list[dict[str, np.ndarray]]:
    """Reset ``world`` at ``starts`` and steer every drone at a point 0.5 m past its next gate of its world's track,
    the drones of a world side by side in the opening, for ``steps`` control steps; the race state after each step."""
    world.reset_all(starts)
    d, history = world.drones_per_world, []
    aims = []  # per drone, the point it steers at behind each gate of its world's track (gates × 3)
    for i in range(world.drone_count):
        t = world.tracks[world.race.world_track.numpy()[i // d]]
        side = 0.1 * (2 * (i % d) / max(d - 1, 1) - 1)
        aims.append(t.gate_centers() + 0.5 * t.gate_forward() + side * t.gate_rotations()[:, :, 1])
    for _ in range(steps):
        gate = world.race.next_gate.numpy()
        cmd = np.zeros((world.drone_count, 4), np.float32)
        for i in range(world.drone_count):
            cmd[i, :3] = aims[i][gate[i]]
        world.cmd.assign(cmd)
        world.step()
        history.append({name: getattr(src, name).numpy().copy() for src, names in (
            (world.state, ("pos", "vel", "quat")), (world.race, ("next_gate", "gates_passed", "out", "pass_time",
                                                                 "step_collision"))) for name in names})
    return history


@pytest.mark.bitwise
def test_worlds_on_different_tracks_step_exactly_as_each_would_alone(kernels, cf2x, circuit6, oval2):
    """Four worlds of two drones race circuit6 and oval2 alternately, in two CPU threads: each world's drones fly,
    pass gates and meet frames and bounds exactly as the same world in a batch of its track alone."""
    tracks = [circuit6, oval2]
    mixed = World(tracks, cf2x, SimCfg(), world_count=4, drones_per_world=2, cpu_threads=2)
    mixed.set_world_tracks(np.array([0, 1, 0, 1]))
    box = lambda t, dx: np.asarray(t.start.center) + np.array([[dx, -0.15, 0.0], [dx, 0.15, 0.0]])  # noqa: E731
    starts = np.concatenate([box(tracks[k % 2], 0.1 * k) for k in range(4)])
    together = _fly_the_gates(mixed, starts, 200)
    for t, track in enumerate(tracks):
        alone = _fly_the_gates(World(track, mixed.airframe, SimCfg(), world_count=2, drones_per_world=2),
                               starts.reshape(4, 2, 3)[t::2].reshape(-1, 3), 200)
        rows = np.concatenate([np.arange(2 * w, 2 * w + 2) for w in (t, t + 2)])
        for step_mixed, step_alone in zip(together, alone, strict=True):
            for name, value in step_alone.items():
                assert np.array_equal(step_mixed[name][rows], value), name  # exact: same arithmetic per drone
    passed = together[-1]["gates_passed"].reshape(4, 2)
    assert passed[0::2].max() >= 1 and passed[1::2].max() >= 1  # drones of both tracks passed gates of their own


def test_world_tracks_must_name_a_track_of_the_world(kernels, cf2x, circuit6):
    world = World([circuit6], cf2x, SimCfg(), world_count=2, drones_per_world=1)
    with pytest.raises(ValueError, match="world_track"):
        world.set_world_tracks(np.array([0, 1]))
    with pytest.raises(ValueError, match="world_track"):
        world.set_world_tracks(np.array([0]))
    with pytest.raises(ValueError, match="track"):
        World([], cf2x, SimCfg(), world_count=1, drones_per_world=1)
