"""Figures: track layouts, the speed-vs-reliability trade-off and learning curves."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from spiral.config.track import TrackSpec

__all__ = ["TradeoffPoint", "plot_learning_curves", "plot_speed_vs_reliability", "plot_track"]

_VIEWS = (("top view (x-y)", 0, 1, "y [m]"), ("side view (x-z)", 0, 2, "z [m]"))
"""Title, horizontal axis, vertical axis and vertical label of each panel."""

_CORNER_LOOP = [0, 1, 3, 2, 0]
"""Order of ``TrackSpec.gate_corners`` rows that walks around the square."""

_GATE_COLOUR = "tab:orange"
_ARROW_COLOUR = "tab:red"
_PAD = 0.3
"""Margin around the arena bounds in each view [m]."""
_ARROW_LENGTH = 0.6
"""Length of a passing-direction arrow before projection [m]."""


def plot_track(track: TrackSpec, out: Path, *, path: np.ndarray | None = None, path_label: str = "path") -> Path:
    """Draw ``track`` in top (x-y) and side (x-z) view and save it as an image.

    Each view shows the arena bounds, the start box, the centreline through the gate centres, every gate's
    outer frame projected onto the view plane, its passing direction as an arrow and its index (from 0).

    Args:
        track: Track to draw.
        out: Image file to write; its suffix picks the format (e.g. ``.png``). Parent folders are created.
        path: Optional positions (T, 3) drawn over both views (e.g. the lap-time reference's flight).
        path_label: Legend label of ``path``.

    Returns:
        The path written.
    """
    # A figure without pyplot: the Agg canvas renders off-screen and no global backend state is touched.
    size, rects = _track_layout(track)
    fig = Figure(figsize=size)
    FigureCanvasAgg(fig)
    axes = [fig.add_axes(rect) for rect in rects]
    for ax, (title, h, v, ylabel) in zip(axes, _VIEWS, strict=True):
        _draw_view(ax, track, h, v)
        if path is not None:
            ax.plot(path[:, h], path[:, v], "-", color="tab:purple", lw=1.4, label=path_label)
        ax.set_title(title, fontsize=11)
        ax.set_xlabel("x [m]")
        ax.set_ylabel(ylabel)
    x, y, w, h = rects[0]
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper left", bbox_to_anchor=(x + w + 0.01, y + h), fontsize=9, frameon=False)
    fig.suptitle(f"{track.name}: {len(track.gates)} gates, centreline {track.centreline_length():.1f} m", fontsize=13)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=150)
    return out


def _label_offset(outward: np.ndarray, forward: np.ndarray, h: int, v: int) -> np.ndarray:
    """Unit 2-D direction for a gate's number: away from the track's middle and away from its arrow."""
    arrow = np.array([forward[h], forward[v]])
    away = np.array([outward[h], outward[v]])
    away = away / max(float(np.linalg.norm(away)), 1e-6) - arrow
    norm = float(np.linalg.norm(away))
    return away / norm if norm > 1e-6 else np.array([0.0, 1.0])


def _track_layout(track: TrackSpec) -> tuple[tuple[float, float], list[tuple[float, float, float, float]]]:
    """Figure size [in] and the two panels' rectangles (figure fractions), top view above side view.

    Both panels use one scale (inches per metre), so with equal aspect their x axes have the same length and
    line up, and no space is lost to aspect adjustment.
    """
    lo, hi = np.asarray(track.bounds.min) - _PAD, np.asarray(track.bounds.max) + _PAD
    span = hi - lo
    scale = min(7.0 / span[0], 9.0 / (span[1] + span[2]))
    left, right, top, gap, bottom = 0.8, 2.0, 0.8, 0.9, 0.6
    width = scale * span[0]
    panel_heights = [scale * span[v] for _, _, v, _ in _VIEWS]
    fig_w, fig_h = left + width + right, top + sum(panel_heights) + gap + bottom
    y_side = bottom
    y_top = bottom + panel_heights[1] + gap
    rects = [
        (left / fig_w, y_top / fig_h, width / fig_w, panel_heights[0] / fig_h),
        (left / fig_w, y_side / fig_h, width / fig_w, panel_heights[1] / fig_h),
    ]
    return (fig_w, fig_h), rects


def _draw_view(ax: Axes, track: TrackSpec, h: int, v: int) -> None:
    """Draw one projection of ``track`` onto its axes ``h`` (horizontal) and ``v`` (vertical)."""
    lo, hi = np.asarray(track.bounds.min), np.asarray(track.bounds.max)
    ax.add_patch(Rectangle((lo[h], lo[v]), hi[h] - lo[h], hi[v] - lo[v], fill=False, ls="--", ec="0.4", label="bounds"))
    s_lo = np.asarray(track.start.center) - np.asarray(track.start.size) / 2
    size = track.start.size
    ax.add_patch(Rectangle((s_lo[h], s_lo[v]), size[h], size[v], fc="tab:green", alpha=0.35, ec="tab:green"))
    ax.plot([], [], "s", color="tab:green", alpha=0.5, label="start box")
    line = track.centreline_points()
    ax.plot(line[:, h], line[:, v], ":", color="tab:blue", lw=1.2, label="centreline")
    _draw_gates(ax, track, h, v)
    ax.set_xlim(lo[h] - _PAD, hi[h] + _PAD)
    ax.set_ylim(lo[v] - _PAD, hi[v] + _PAD)
    ax.set_aspect("equal")
    ax.grid(True, color="0.9", lw=0.6)


def _draw_gates(ax: Axes, track: TrackSpec, h: int, v: int) -> None:
    """Draw gate frames, passing-direction arrows and gate indices in one projection."""
    centres, forward = track.gate_centers(), track.gate_forward()
    middle = centres.mean(axis=0)
    for i, c in enumerate(centres):
        frame = track.gate_corners(i)[_CORNER_LOOP]
        ax.plot(frame[:, h], frame[:, v], color=_GATE_COLOUR, lw=2.5, solid_capstyle="round",
                label="gate frame" if i == 0 else None)
        tip = forward[i] * _ARROW_LENGTH
        ax.annotate(
            "",
            xy=(c[h] + tip[h], c[v] + tip[v]),
            xytext=(c[h], c[v]),
            arrowprops={"arrowstyle": "-|>", "color": _ARROW_COLOUR, "lw": 1.8, "mutation_scale": 14},
        )
        at = np.array([c[h], c[v]]) + _label_offset(c - middle, forward[i], h, v) * (0.5 * track.gate_size(i) + 0.25)
        ax.text(*at, str(i), ha="center", va="center", fontsize=11, fontweight="bold",
                bbox={"boxstyle": "circle,pad=0.2", "fc": "white", "ec": _GATE_COLOUR})
    ax.plot([], [], color=_ARROW_COLOUR, marker=">", label="passing direction")


@dataclass(frozen=True)
class TradeoffPoint:
    """One method in one scenario on the speed-vs-reliability plot."""

    label: str
    """Method name (one colour per label)."""
    scenario: str
    """``1v1`` (circle) or ``2v2`` (square)."""
    lap_time: float
    """Mean lap time of successful drones [s]."""
    success: float
    """Success ratio."""
    lap_std: float = 0.0
    """Horizontal error bar [s]."""
    success_ci: tuple[float, float] | None = None
    """Vertical error bar (e.g. the 95% Wilson interval)."""
    paper: bool = False
    """A number quoted from the paper (hollow marker) rather than measured here."""


_MARKERS = {"solo": "^", "1v1": "o", "2v2": "s"}
_PALETTE = ("tab:red", "tab:blue", "tab:gray", "tab:green", "tab:purple", "tab:brown")


def plot_speed_vs_reliability(points: Sequence[TradeoffPoint], out: Path, *, bound: float | None = None,
                              title: str = "Speed vs. reliability") -> Path:
    """The paper's Fig. 3: lap time (x, lower is better) against success ratio (y), 1v1 circles, 2v2 squares.

    Measured points are filled with error bars; the paper's numbers are hollow. ``bound`` draws the point-mass
    lap-time reference as a vertical line.
    """
    fig = Figure(figsize=(7.5, 5.2))
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    colours = {label: _PALETTE[i % len(_PALETTE)] for i, label in enumerate(dict.fromkeys(p.label for p in points))}
    for p in points:
        c, m = colours[p.label], _MARKERS.get(p.scenario, "D")
        if p.paper:
            ax.plot(p.lap_time, p.success, m, mfc="none", mec=c, ms=10, mew=1.5, alpha=0.7)
            continue
        yerr = None
        if p.success_ci is not None:
            yerr = [[max(p.success - p.success_ci[0], 0.0)], [max(p.success_ci[1] - p.success, 0.0)]]
        ax.errorbar(p.lap_time, p.success, xerr=p.lap_std or None, yerr=yerr, fmt=m, color=c, ms=9, capsize=3,
                    elinewidth=1)
    if bound is not None:
        ax.axvline(bound, ls="--", color="0.3", lw=1)
        ax.text(bound, 0.02, " point-mass bound", fontsize=8, va="bottom", ha="left", color="0.3", rotation=90)
    handles = [ax.plot([], [], "o", color=c, label=label)[0] for label, c in colours.items()]
    handles += [ax.plot([], [], _MARKERS[s], color="0.3", label=s)[0] for s in ("1v1", "2v2")
                if any(p.scenario == s for p in points)]
    if any(p.paper for p in points):
        handles.append(ax.plot([], [], "o", mfc="none", mec="0.3", label="paper (hollow)")[0])
    ax.legend(handles=handles, fontsize=8, loc="lower right", frameon=False)
    ax.set_xlabel("lap time [s] (lower is better)")
    ax.set_ylabel("success ratio (higher is better)")
    ax.set_ylim(-0.02, 1.08)
    ax.text(0.01, 0.98, "ideal region ↖", transform=ax.transAxes, fontsize=8, va="top", color="0.4")
    ax.grid(True, color="0.9", lw=0.6)
    ax.set_title(title, fontsize=11)
    return _save(fig, out)


_CURVES = (("reward_per_step", "reward per step"), ("success", "success ratio (training episodes)"),
           ("lap_time", "lap time [s] (successful episodes)"))


def plot_learning_curves(logs: dict[str, list[dict[str, float]]], out: Path, *, smooth: int = 5) -> Path:
    """Reward, success and lap time per PPO iteration, one line per stage (raw faint, moving average bold).

    Args:
        logs: Rows of each stage's ``train_log.jsonl`` by stage name (``iteration`` and the plotted keys).
        out: Image file to write.
        smooth: Window of the moving average [iterations].
    """
    fig = Figure(figsize=(8.5, 8))
    FigureCanvasAgg(fig)
    axes = fig.subplots(len(_CURVES), 1, sharex=True)
    for i, (stage, rows) in enumerate(logs.items()):
        colour = _PALETTE[i % len(_PALETTE)]
        it = np.array([r.get("iteration", k) for k, r in enumerate(rows)], dtype=float)
        for ax, (key, _) in zip(axes, _CURVES, strict=True):
            y = np.array([_number(r.get(key)) for r in rows])
            if not np.isfinite(y).any():
                continue
            ax.plot(it, y, color=colour, lw=0.6, alpha=0.3)
            ax.plot(it, _moving_average(y, smooth), color=colour, lw=1.6, label=stage)
    for ax, (_, label) in zip(axes, _CURVES, strict=True):
        ax.set_ylabel(label, fontsize=9)
        ax.grid(True, color="0.9", lw=0.6)
    axes[0].legend(fontsize=8, frameon=False, ncol=max(1, min(len(logs), 5)))
    axes[-1].set_xlabel("PPO iteration (per stage)")
    fig.suptitle("Learning curves", fontsize=12)
    return _save(fig, out)


def _number(value: object) -> float:
    return float(value) if isinstance(value, int | float) and math.isfinite(value) else float("nan")


def _moving_average(y: np.ndarray, window: int) -> np.ndarray:
    """Trailing mean over the finite values of the last ``window`` entries (NaN where there are none)."""
    out = np.full_like(y, np.nan)
    for k in range(len(y)):
        chunk = y[max(0, k - window + 1):k + 1]
        chunk = chunk[np.isfinite(chunk)]
        if chunk.size:
            out[k] = chunk.mean()
    return out


def _save(fig: Figure, out: Path) -> Path:
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=130)
    return out
