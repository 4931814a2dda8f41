"""Contracts every layer of spiral shares, at the bottom of the import order (``core`` imports no other package).

- :mod:`spiral.core.scenario`: the scenarios: drones per world, the teams' slots, the slots a stage's learner
  drives.
- :mod:`spiral.core.outcome`: who won a race, from the drones' finish times.
- :mod:`spiral.core.policy`: what a policy and an opponent policy are (``typing.Protocol``\\ s).
- :mod:`spiral.core.files`: atomic writes and checksums.
- :mod:`spiral.core.checkpoint`: the checkpoint format, frozen policies and loading them.
- :mod:`spiral.core.inputs`: inputs a stored policy never saw vary, and silencing them.
- :mod:`spiral.core.errors`: the error a user can fix (``UsageError``).
- :mod:`spiral.core.seeds`: the random streams of a stage and their seeds.

The package imports none of its modules, so ``spiral.config`` (and through it ``spiral.sim``) reads the scenario
table without loading torch; import each name from its module.
"""

from __future__ import annotations

__all__: list[str] = []
