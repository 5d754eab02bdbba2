"""Robots of planar bodies with absolute joint angles: the thesis' 2-D four-bar (seed 004 §2.5).

The bodies use the "planar" convention (`jaxcal.kin.joints.planar`): body j carries a length a_j and
an angle offset phi_j, its frame has the absolute angle theta_j + phi_j and sits at the end of its
predecessor's link (eq 2.72-2.76). The parameter vector is (a_1..a_N, phi_1..phi_N).
"""

from __future__ import annotations

import numpy as np

from jaxcal.closure.core import Closure
from jaxcal.kin.model import Body, Robot


def planar_robot(name, lengths, offsets, predecessors, actuated, closure: Closure, tip, home=None,
                 q_min=None, q_max=None) -> Robot:
    """Robot of planar absolute-angle bodies 1..N (predecessor 0 = base).

    Parameters are named "j{i}.a" (lengths) then "j{i}.phi" (offsets), i = 1..N.
    """
    n = len(lengths)
    if len(offsets) != n or len(predecessors) != n:
        raise ValueError(f"planar robot {name!r}: lengths, offsets and predecessors must have one entry per body ({n})")
    bodies = []
    for i, pred in enumerate(predecessors, start=1):
        if not 0 <= int(pred) < i:
            raise ValueError(f"planar robot {name!r}, body {i}: predecessor {pred} must name an earlier body (0 = base)")
        inputs = (list(actuated).index(i),) if i in actuated else ()
        bodies.append(Body(f"j{i}", "planar", 0, int(pred) - 1, (i - 1, n + i - 1), inputs))
    names = tuple(f"j{i}.a" for i in range(1, n + 1)) + tuple(f"j{i}.phi" for i in range(1, n + 1))
    n_in = len(actuated)
    return Robot(
        name=name, bodies=tuple(bodies), names=names,
        nominal_np=np.concatenate([np.asarray(lengths, float), np.asarray(offsets, float)]),
        units=("length",) * n + ("angle",) * n, free_mask=np.ones(2 * n, bool), priority=np.ones(2 * n),
        joint_names=tuple(f"j{i}" for i in actuated),
        home_np=np.zeros(n_in) if home is None else np.asarray(home, float),
        q_min=np.full(n_in, -np.pi) if q_min is None else np.asarray(q_min, float),
        q_max=np.full(n_in, np.pi) if q_max is None else np.asarray(q_max, float),
        tip=tip - 1, closure=closure,
    )
