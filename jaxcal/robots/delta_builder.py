"""A Delta robot of any dimensions in the layout of seed 004 Table 4.6 (issue 16).

`delta_robot(DeltaGeometry(...))` writes the 30 MCPC rows of Table 4.6 (Table 4.1 columns a1 a2 a3 d1 d2 d3
predecessor closure type; same bodies, predecessors, closures, types and actuated bodies) from the nominal
dimensions of §2.6 and returns it with the Delta closure (`jaxcal.closure.delta`, whose fast path starts from
the direct solution of these dimensions) and Table 4.6's free parameters:

- 1: the base frame; 2, 3, 4: arm i at [-pi/2, -psi_i, 0, rb, 0, 0]: V = Rx(-pi/2) Ry(-psi_i) turns the joint
  axis to the elbow-axis direction (-sin psi_i, cos psi_i, 0), the arm lies along (cos psi_i, sin psi_i, 0)
  at radius rb and theta_i turns it below the horizontal (eq 2.114);
- each rod k = 1..6 (two per arm, k = 2i - 1, 2i): elbow [0, 0, 0, n] on its arm, universal joint
  [pi/2, 0, 0, 0, +-spread] (the parallelogram, + for odd k), rod [0, 0, 0, m]; rod 1 is bodies 5-7 and
  carries the simulated ball joint 7-8-9 and the nacelle 9; rods 2-6 are 15-17, 18-20, ..., 27-29;
- 10-14: the nacelle ends of rods 2-6 (spherical closures with 17, 20, 23, 26, 29) and 30: the tool, both
  in the nacelle frame (`jaxcal.closure.delta.nacelle_local`).
"""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.closure import delta as dl
from jaxcal.closure.delta import NOMINAL, DeltaGeometry
from jaxcal.robots.build import mcpc_robot
from jaxcal.robots.builtin import free_list

TABLE_4_6_HOME = (0.5, 0.5, 0.5)  # rad: delta.yaml's home and joint limits
TABLE_4_6_LIMITS = (-0.2, 1.4)
REACH_GRID = 5  # settings per actuator at which the rods must reach the nacelle (corners included)


def table_rows(g: DeltaGeometry) -> list[list[float]]:
    """The 30 rows of Table 4.6 written from the dimensions g (module docstring)."""
    rows = {1: [0.0] * 6 + [0, 0, 3]}
    for arm, psi in zip(dl.ACTUATORS, g.psi):
        rows[arm] = [-np.pi / 2, -psi, 0.0, g.rb, 0.0, 0.0, 1, 0, 0]
    for k, (elbow, universal, end) in enumerate((dl.ROD1[:3],) + dl.RODS):
        arm, side = divmod(k, 2)
        rows[elbow] = [0.0, 0.0, 0.0, g.n, 0.0, 0.0, dl.ACTUATORS[arm], 0, 0]
        rows[universal] = [np.pi / 2, 0.0, 0.0, 0.0, (-g.spread if side else g.spread), 0.0, elbow, 0, 0]
        rows[end] = [0.0, 0.0, 0.0, g.m, 0.0, 0.0, universal, 0, 0]
    rows[8] = [np.pi / 2, 0.0, 0.0, 0.0, 0.0, 0.0, 7, 0, 0]  # ball joint 7-8-9
    rows[dl.NACELLE] = [0.0, -np.pi / 2, 0.0, 0.0, 0.0, 0.0, 8, 0, 0]
    for body, (_, _, end), point in zip(dl.CLOSURES, dl.RODS, dl.nacelle_local(dl.rod_ends(g)[1:], g)):
        rows[body] = [0.0, 0.0, 0.0, *point, dl.NACELLE, end, 2]
    rows[dl.TOOL] = [0.0, 0.0, 0.0, *dl.nacelle_local(g.tool, g), dl.NACELLE, 0, 3]
    return [[float(v) for v in rows[k][:6]] + [int(v) for v in rows[k][6:]] for k in range(1, dl.TOOL + 1)]


def _settings(home, q_min, q_max) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """home, q_min, q_max as (3,) arrays, checked: finite and q_min <= home <= q_max, q_min < q_max."""
    home, lo, hi = (np.broadcast_to(np.asarray(v, dtype=float), (3,)).copy() for v in (home, q_min, q_max))
    if not all(np.all(np.isfinite(v)) for v in (home, lo, hi)):
        raise ValueError(f"Delta: home, q_min, q_max must be finite (rad), got {home}, {lo}, {hi}")
    if np.any(lo >= hi) or np.any(home < lo) or np.any(home > hi):
        raise ValueError(f"Delta: need q_min < q_max and q_min <= home <= q_max (rad), got {lo}, {home}, {hi}")
    return home, lo, hi


def _check_reach(g: DeltaGeometry, home, lo, hi):
    """Raise unless the nominal direct solution (eq 2.135-2.146) exists at home and on a REACH_GRID^3 grid
    of the joint box: the three rod spheres must meet (h2 >= 0), which fails when the rods are too short."""
    axes = [np.linspace(a, b, REACH_GRID) for a, b in zip(lo, hi)]
    theta = np.vstack([home, np.array(list(itertools.product(*axes)))])
    P, ok = jax.vmap(lambda t: dl.direct(t, g))(jnp.asarray(theta))
    bad = ~(np.asarray(ok) & np.all(np.isfinite(np.asarray(P)), axis=-1))
    if np.any(bad):
        where = np.round(theta[np.argmax(bad)], 4).tolist()
        raise ValueError(f"Delta: the rods (m = {g.m} m) do not reach the nacelle at actuator angles {where} rad "
                         f"within q_min {lo.tolist()} .. q_max {hi.tolist()} (no nominal direct solution, seed 004 "
                         "§2.6, at that setting): lengthen m, shorten n or rb - rn, or narrow the joint limits")


def delta_robot(geometry: DeltaGeometry = NOMINAL, *, name: str = "delta", home=TABLE_4_6_HOME,
                q_min=TABLE_4_6_LIMITS[0], q_max=TABLE_4_6_LIMITS[1], free=None):
    """A Delta of the given dimensions (`DeltaGeometry`: rb, rn, n, m, psi, spread, tool) as the 30-body
    MCPC model of seed 004 Table 4.6, closed by `jaxcal.closure.delta` (its fast path starts from this
    geometry's nominal direct solution). Joints theta1..3 (rad, below the horizontal); home and limits
    default to Table 4.6's; the rods must reach the nacelle over the joint limits. `free`: names of the
    parameters to identify (default: those Table 4.6 marks, as the built-in "delta"). At `NOMINAL` it is
    Table 4.6 with the nacelle points at full precision (`jaxcal.closure.delta.full_precision_nominal`)."""
    home, lo, hi = _settings(home, q_min, q_max)
    _check_reach(geometry, home, lo, hi)
    names = tuple(free_list("delta.yaml") if free is None else free)
    robot = mcpc_robot(name, table_rows(geometry), actuated=dl.ACTUATORS, home=home, q_min=lo, q_max=hi,
                       joint_names=("theta1", "theta2", "theta3"), tip=dl.TOOL)
    unknown = sorted(set(names) - set(robot.names))
    if unknown:
        raise ValueError(f"Delta: no parameters {unknown} in the Table 4.6 layout (names are j<body>.<a1..d3>)")
    return dl.with_delta_closure(robot, free=names, geometry=geometry)
