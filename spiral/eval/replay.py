"""Race replays: record one race of any methods and render it as a GIF or MP4.

A frame shows the top (x-y) and side (x-z) views with the gate frames, each drone's recent trail in its team's
colour, a cross where a drone crashed and a star where it finished, and a panel with the race time and each
drone's gate and lap counters. Frames are drawn with matplotlib's Agg canvas (no GUI) at ``fps`` frames per
second of race time; GIFs are written by Pillow, MP4s by an ``ffmpeg`` executable when one is available.
"""

from __future__ import annotations

import math
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from PIL import Image

from spiral.config.airframe import AirframeCfg
from spiral.config.sim import SimCfg
from spiral.config.track import TrackSpec
from spiral.core.errors import UsageError
from spiral.core.scenario import TEAMS
from spiral.env.race_env import RaceEnv
from spiral.eval.evaluate import EvalLayout, RaceSet, load_method, race_device, setup_race
from spiral.eval.plots import _draw_view
from spiral.sim import COLLISION_KINDS

__all__ = ["RaceRecording", "frame_count", "record_race", "render_race"]

TEAM_COLOURS = ("tab:red", "tab:blue")
"""Colour of team A and team B."""

_HOLD_LAST_S = 1.5
"""How long a GIF shows its last frame [s]."""


@dataclass
class RaceRecording:
    """State of every drone of one race at every control step."""

    track: TrackSpec
    scenario: str
    team_names: list[str]
    """Method name of each team."""
    dt: float
    """Control step [s]."""
    pos: np.ndarray
    """Positions (T, D, 3) [m]."""
    gates: np.ndarray
    """Gates passed in order (T, D)."""
    crashed: np.ndarray
    """Crashed by then (T, D)."""
    finished: np.ndarray
    """Finished by then (T, D)."""
    crash_kind: np.ndarray
    """Collision bits of each drone's crash (D,)."""
    lap_time: np.ndarray
    """Finishing time (D,), 0 when not finished [s]."""
    passes_needed: int
    """Gate passes of a complete race."""

    @property
    def duration(self) -> float:
        """Race time covered by the recording [s]."""
        return (len(self.pos) - 1) * self.dt

    @property
    def teams(self) -> list[list[int]]:
        """Drone slots of each team."""
        return TEAMS[self.scenario] if len(self.team_names) > 1 else [list(range(self.pos.shape[1]))]

    def outcomes(self) -> list[str]:
        """One line per drone: its slot, its team's method and how its race ended (lap time, or the kinds of its
        crash, or still racing) with the gates it passed."""
        lines = []
        for name, slots in zip(self.team_names, self.teams, strict=True):
            for d in slots:
                gates = int(self.gates[-1, d])
                if self.finished[-1, d]:
                    end = f"finished in {float(self.lap_time[d]):.2f} s"
                elif self.crashed[-1, d]:
                    kinds = [k for k, bit in COLLISION_KINDS.items() if int(self.crash_kind[d]) & bit]
                    end = f"crashed ({', '.join(kinds) or 'unknown'}) after {gates} of {self.passes_needed} gate passes"
                else:
                    end = f"still racing after {gates} of {self.passes_needed} gate passes"
                lines.append(f"drone {d} ({name}): {end}")
        return lines


def record_race(track: TrackSpec, scenario: str, method: tuple[str, str], against: tuple[str, str] | None = None,
                *, seed: int = 0, device: str = "cpu", airframe: AirframeCfg | None = None,
                sim: SimCfg | None = None) -> RaceRecording:
    """Fly one race from the start placement of ``seed`` (that of a one-race ``spiral eval``) and record it.

    Args:
        track: Track to race on.
        scenario: ``solo``, ``1v1`` or ``2v2``.
        method: (name, checkpoint or ``se-ibr``) flying every drone, or team A when ``against`` is given.
        against: (name, checkpoint or ``se-ibr``) of team B.
        seed: Seed of the start placement.
        device: Torch/Warp device (the CPU when SE-IBR flies).
        airframe: Airframe when no learned policy is involved (default cf2x).
        sim: Simulator settings when no learned policy is involved.
    """
    device = race_device(device, [method[1], *([against[1]] if against is not None else [])])
    policy = load_method(method[1], device=device)
    opponent = load_method(against[1], device=device) if against is not None else None
    layout = EvalLayout.default(airframe=airframe, sim=sim)
    env, learner = setup_race(RaceSet(track, scenario, 1, seed), policy, opponent, device=device, layout=layout)
    obs = env.reset()
    snaps = [_snapshot(env)]
    for _ in range(env.max_episode_length):
        with torch.no_grad():
            obs, _, _, _ = env.step(learner(obs))
        snaps.append(_snapshot(env))
        if not bool(env.records.racing().any()):
            break
    pos, gates, crashed, finished = (np.stack(x) for x in zip(*snaps, strict=True))
    names = [method[0]] + ([against[0]] if against is not None else [])
    return RaceRecording(track, scenario, names, float(env.dt), pos, gates, crashed, finished,
                         env.records.crash_kind.cpu().numpy(), env.records.lap_time.cpu().numpy(), env.passes_needed)


def _snapshot(env: RaceEnv) -> tuple[np.ndarray, ...]:
    rec = env.records
    return (env.pos.cpu().numpy().copy(), env.gates_passed.cpu().numpy().copy(), rec.crashed.cpu().numpy().copy(),
            rec.finished.cpu().numpy().copy())


def frame_count(duration: float, fps: float, *, speed: float = 1.0) -> int:
    """Frames of a replay of ``duration`` seconds: one every ``speed / fps`` seconds of race time from the start,
    and one more at the end when the race does not end on a frame (it shows the final state)."""
    return math.ceil(duration * fps / speed - 1e-9) + 1


def render_race(rec: RaceRecording, out: Path, *, fps: float = 15.0, speed: float = 1.0, trail_s: float = 3.0,
                dpi: int = 80) -> int:
    """Render ``rec`` to ``out`` (``.gif`` or ``.mp4``) and return the number of frames written.

    Args:
        rec: The recorded race.
        out: Output file; its suffix picks the format.
        fps: Frames per second of the video.
        speed: Race seconds per video second.
        trail_s: Length of the drawn trail behind each drone [s of race time].
        dpi: Resolution of the 10 × 5.2 inch frames.
    """
    out = Path(out)
    if out.suffix.lower() not in (".gif", ".mp4"):
        raise UsageError(f"{out}: replay must be a .gif or .mp4 file")
    count = frame_count(rec.duration, fps, speed=speed)
    steps = np.minimum(np.rint(np.arange(count) * speed / fps / rec.dt).astype(int), len(rec.pos) - 1)
    scene = _Scene(rec, dpi=dpi, trail_steps=max(1, round(trail_s / rec.dt)))
    frames = [scene.draw(int(k)) for k in steps]
    out.parent.mkdir(parents=True, exist_ok=True)
    if out.suffix.lower() == ".gif":
        _write_gif(frames, out, fps)
    else:
        _write_mp4(frames, out, fps)
    return len(frames)


@dataclass
class _DroneArtists:
    """The artists of one drone in one view (horizontal axis ``h``, vertical axis ``v``)."""

    h: int
    v: int
    trail: Line2D
    head: Line2D
    crash: Line2D
    finish: Line2D


class _Scene:
    """A figure with static track drawings and per-drone artists updated frame by frame."""

    def __init__(self, rec: RaceRecording, *, dpi: int, trail_steps: int) -> None:
        self.rec, self.trail_steps = rec, trail_steps
        self.fig = Figure(figsize=(10, 5.2), dpi=dpi)
        self.canvas = FigureCanvasAgg(self.fig)
        grid = self.fig.add_gridspec(2, 2, width_ratios=[1.15, 1.0], height_ratios=[1.0, 1.0])
        top, side = self.fig.add_subplot(grid[:, 0]), self.fig.add_subplot(grid[0, 1])
        self.info = self.fig.add_subplot(grid[1, 1])
        self.info.axis("off")
        self.views = [(top, 0, 1), (side, 0, 2)]
        for ax, h, v in self.views:
            _draw_view(ax, rec.track, h, v)
            ax.tick_params(labelsize=7)
        top.set_title("top view (x-y)", fontsize=9)
        side.set_title("side view (x-z)", fontsize=9)
        self.colour = np.empty(rec.pos.shape[1], dtype=object)
        for t, slots in enumerate(rec.teams):
            self.colour[slots] = TEAM_COLOURS[t % len(TEAM_COLOURS)]
        self.artists = [self._drone_artists(ax, h, v) for ax, h, v in self.views]
        self.text = self.info.text(0.0, 1.0, "", va="top", ha="left", family="monospace", fontsize=9,
                                   transform=self.info.transAxes, animated=True)
        self.fig.subplots_adjust(left=0.06, right=0.98, top=0.93, bottom=0.07, wspace=0.18, hspace=0.3)
        # Blitting: the static track is rendered once; each frame restores it and draws the animated artists.
        self.canvas.draw()
        self.background = self.canvas.copy_from_bbox(self.fig.bbox)

    def _drone_artists(self, ax: Axes, h: int, v: int) -> list[_DroneArtists]:
        out = []
        for d in range(self.rec.pos.shape[1]):
            c = self.colour[d]
            out.append(_DroneArtists(
                h, v,
                trail=ax.plot([], [], "-", color=c, lw=1.6, alpha=0.8, animated=True)[0],
                head=ax.plot([], [], "o", color=c, ms=6, mec="black", mew=0.6, animated=True)[0],
                crash=ax.plot([], [], "x", color="black", ms=11, mew=2.5, animated=True)[0],
                finish=ax.plot([], [], "*", color=c, ms=14, mec="black", mew=0.6, animated=True)[0],
            ))
        return out

    def draw(self, k: int) -> np.ndarray:
        """RGB image of control step ``k``."""
        rec = self.rec
        lo = max(0, k - self.trail_steps)
        self.canvas.restore_region(self.background)
        for (ax, _, _), view in zip(self.views, self.artists, strict=True):
            for d, art in enumerate(view):
                p = rec.pos[lo:k + 1, d]
                x, y = p[:, art.h], p[:, art.v]
                art.trail.set_data(x, y)
                art.head.set_data(x[-1:], y[-1:])
                art.crash.set_data(x[-1:] if rec.crashed[k, d] else [], y[-1:] if rec.crashed[k, d] else [])
                art.finish.set_data(x[-1:] if rec.finished[k, d] else [], y[-1:] if rec.finished[k, d] else [])
                for line in (art.trail, art.head, art.crash, art.finish):
                    ax.draw_artist(line)
        self.text.set_text(self._status(k))
        self.info.draw_artist(self.text)
        return np.asarray(self.canvas.buffer_rgba())[..., :3].copy()

    def _status(self, k: int) -> str:
        rec, g = self.rec, len(self.rec.track.gates)
        lines = [f"{rec.track.name}  {rec.scenario}   t = {k * rec.dt:5.2f} s", ""]
        for t, slots in enumerate(rec.teams):
            lines.append(f"team {'AB'[t]} ({TEAM_COLOURS[t % 2].removeprefix('tab:')}): {rec.team_names[t]}")
            for d in slots:
                passes = int(rec.gates[k, d])
                laps = max(0, passes - 1) // g
                state = f"gate {passes:2d}/{rec.passes_needed}  lap {laps}/{rec.track.laps}"
                if rec.finished[k, d]:
                    state = f"finished in {rec.lap_time[d]:.2f} s"
                elif rec.crashed[k, d]:
                    kinds = [n for n, bit in COLLISION_KINDS.items() if int(rec.crash_kind[d]) & bit]
                    state = f"crashed ({', '.join(kinds) or 'collision'}) at gate {passes}"
                lines.append(f"  drone {d}: {state}")
        return "\n".join(lines)


def _write_gif(frames: list[np.ndarray], out: Path, fps: float) -> None:
    # One palette for every frame (the last frame holds every colour the race uses): fast and small.
    palette = Image.fromarray(frames[-1]).quantize(colors=96, method=Image.Quantize.FASTOCTREE,
                                                   dither=Image.Dither.NONE)
    images = [Image.fromarray(f).quantize(palette=palette, dither=Image.Dither.NONE) for f in frames]
    # GIF delays are whole centiseconds: round the frame start times, not the delays, so playback keeps real time.
    starts = np.rint(np.arange(len(images) + 1) * 100.0 / fps).astype(int)
    durations = [10 * int(d) for d in np.diff(starts)]
    durations[-1] = max(durations[-1], round(1000 * _HOLD_LAST_S))
    images[0].save(out, save_all=True, append_images=images[1:], duration=durations, loop=0, disposal=1)


def _ffmpeg() -> str | None:
    exe = shutil.which("ffmpeg")
    if exe is not None:
        return exe
    try:
        import imageio_ffmpeg  # optional: ships an ffmpeg binary
    except ImportError:
        return None
    return imageio_ffmpeg.get_ffmpeg_exe()


def _write_mp4(frames: list[np.ndarray], out: Path, fps: float) -> None:
    exe = _ffmpeg()
    if exe is None:
        raise UsageError(f"{out}: writing .mp4 needs ffmpeg on PATH (or the imageio-ffmpeg package); "
                         "write a .gif instead")
    height, width = frames[0].shape[:2]
    cmd = [exe, "-y", "-loglevel", "error", "-f", "rawvideo", "-pix_fmt", "rgb24", "-s", f"{width}x{height}",
           "-r", f"{fps}", "-i", "-", "-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2", "-pix_fmt", "yuv420p",
           "-c:v", "libx264", str(out)]
    proc = subprocess.run(cmd, input=b"".join(f.tobytes() for f in frames), capture_output=True, check=False)
    if proc.returncode != 0:
        raise UsageError(f"{out}: ffmpeg failed: {proc.stderr.decode(errors='replace').strip()}")
