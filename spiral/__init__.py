"""spiral: self-play training of autonomous racing drones."""

from __future__ import annotations

__all__ = ["__version__"]

__version__ = "0.1.0"
