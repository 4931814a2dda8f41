"""Figures: track layouts in top and side view."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from spiral.config.track import TrackSpec

__all__ = ["plot_track"]

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


def plot_track(track: TrackSpec, out: Path) -> Path:
    """Draw ``track`` in top (x-y) and side (x-z) view and save it as an image.

    Each view shows the arena bounds, the start box, the centreline through the gate centres, every gate's
    outer frame projected onto the view plane, its passing direction as an arrow and its index (from 0).

    Args:
        track: Track to draw.
        out: Image file to write; its suffix picks the format (e.g. ``.png``). Parent folders are created.

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
