"""Closure descriptions from seed 004 Table 4.1 rows (a1 a2 a3 d1 d2 d3 predecessor closure type)."""

from __future__ import annotations

from jaxcal.closure.core import Closure

ROTARY, PRISMATIC, SPHERICAL, AUXILIARY = 0, 1, 2, 3


def closure_from_rows(rows, actuated, start=None, **options) -> Closure:
    """The closure pairs and free joints a Table 4.1 table implies (seed 004 §2.4.1, §2.5.2).

    Row i with closure column j != 0 closes with body j: a "position" pair when either is spherical
    (type 2), else "full". Free joints: rotary/prismatic bodies that are not actuated, minus the body
    carrying the closure column of each rotary/prismatic pair (one joint of the pair), minus both
    bodies of a spherical pair; auxiliary frames (type 3) are never free. start defaults to zeros.
    """
    actuated = {int(b) for b in actuated}
    types = {i: int(row[8]) for i, row in enumerate(rows, start=1)}
    pairs, not_free = [], set()
    for i, row in enumerate(rows, start=1):
        j = int(row[7])
        if j == 0:
            continue
        if j not in types or j == i:
            raise ValueError(f"row {i}: field 'closure' = {j} must name another row 1..{len(rows)}")
        spherical = SPHERICAL in (types[i], types[j])
        pairs.append((j, i, "position" if spherical else "full"))
        not_free |= {i, j} if spherical else {i}
    free = tuple(i for i, t in types.items() if t in (ROTARY, PRISMATIC) and i not in actuated and i not in not_free)
    start = (0.0,) * len(free) if start is None else tuple(float(s) for s in start)
    return Closure(pairs=tuple(pairs), free=free, start=start, **options)
