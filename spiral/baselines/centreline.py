"""Track geometry for the planner: a smooth reference line through the gates, progress along it, gate frames."""

from __future__ import annotations

import numpy as np

from spiral.config.track import TrackSpec

__all__ = ["Centreline"]


def _catmull_rom(points: np.ndarray, samples: int) -> np.ndarray:
    """Closed centripetal Catmull–Rom spline through ``points`` (P, 3), ``samples`` points per span."""
    p = np.concatenate([points[-1:], points, points[:2]], axis=0)
    out = []
    u = np.linspace(0.0, 1.0, samples, endpoint=False)[:, None]
    for i in range(1, len(points) + 1):
        p0, p1, p2, p3 = p[i - 1], p[i], p[i + 1], p[i + 2]
        t1 = np.linalg.norm(p1 - p0) ** 0.5 + 1e-9
        t2 = t1 + np.linalg.norm(p2 - p1) ** 0.5 + 1e-9
        t3 = t2 + np.linalg.norm(p3 - p2) ** 0.5 + 1e-9
        t = t1 + u * (t2 - t1)
        a1 = (t1 - t) / t1 * p0 + t / t1 * p1
        a2 = (t2 - t) / (t2 - t1) * p1 + (t - t1) / (t2 - t1) * p2
        a3 = (t3 - t) / (t3 - t2) * p2 + (t - t2) / (t3 - t2) * p3
        b1 = (t2 - t) / t2 * a1 + t / t2 * a2
        b2 = (t3 - t) / (t3 - t1) * a2 + (t - t1) / (t3 - t1) * a3
        out.append((t2 - t) / (t2 - t1) * b1 + (t - t1) / (t2 - t1) * b2)
    return np.concatenate(out, axis=0)


class Centreline:
    """A closed reference line that passes every gate centre along the gate's passing direction.

    Control points are ``c_g − a_g·f_g, c_g, c_g + a_g·f_g`` for each gate ``g`` (``a_g`` = ``approach`` capped at
    a quarter of the distance to the neighbouring gates), joined by a centripetal Catmull–Rom spline sampled every
    few centimetres. The planner uses it only for the progress direction (its tangent) and first guesses; the hard
    geometry (gate openings) is in the gate frames.
    """

    def __init__(self, track: TrackSpec, *, approach: float = 0.5, samples: int = 24) -> None:
        c, f = track.gate_centers(), track.gate_forward()
        rot = track.gate_rotations()
        self.gate_count = len(c)
        self.center, self.forward = c, f
        self.axis_y, self.axis_z = rot[:, :, 1], rot[:, :, 2]
        self.half_opening = np.array([track.gate_opening(i) / 2.0 for i in range(self.gate_count)])
        gap = np.linalg.norm(c - np.roll(c, 1, axis=0), axis=1)
        a = np.minimum(approach, 0.25 * np.minimum(gap, np.roll(gap, -1)))
        ctrl = np.stack([c - a[:, None] * f, c, c + a[:, None] * f], axis=1).reshape(-1, 3)
        pts = _catmull_rom(ctrl, samples)
        self.points = pts
        seg = np.linalg.norm(np.roll(pts, -1, axis=0) - pts, axis=1)
        self.arc = np.concatenate([[0.0], np.cumsum(seg)[:-1]])
        self.length = float(seg.sum())
        tan = np.roll(pts, -1, axis=0) - np.roll(pts, 1, axis=0)
        self.tangent = tan / np.linalg.norm(tan, axis=1, keepdims=True)
        self.samples_per_gate = 3 * samples
        self.gate_sample = np.arange(self.gate_count) * self.samples_per_gate + samples
        """Index of the sample at each gate centre."""
        self.exit_sample = self.gate_sample + samples // 2

    def window(self, gate: int) -> np.ndarray:
        """Sample indices from the previous gate's centre to half-way past ``gate``'s exit point (wrapping)."""
        start = self.gate_sample[(gate - 1) % self.gate_count]
        stop = self.exit_sample[gate % self.gate_count]
        n = len(self.points)
        return np.arange(start, stop + (n if stop <= start else 0)) % n

    def project(self, p: np.ndarray, gates: np.ndarray) -> np.ndarray:
        """Closest sample index to each point ``p`` (K, 3) within the window of its target gate ``gates`` (K,)."""
        out = np.empty(len(p), dtype=np.int64)
        for g in np.unique(gates):
            sel = gates == g
            win = self.window(int(g))
            d = ((p[sel][:, None, :] - self.points[win][None]) ** 2).sum(-1)
            out[sel] = win[d.argmin(axis=1)]
        return out

    def depth(self, p: np.ndarray, gates: np.ndarray) -> np.ndarray:
        """Signed distance of ``p`` (..., 3) past the plane of gate ``gates`` (...) along its passing direction."""
        g = gates % self.gate_count
        return ((p - self.center[g]) * self.forward[g]).sum(-1)
