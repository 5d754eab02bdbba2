"""Population-wide forward kinematics and pose fitness for PRY module chains (seed 000 eq 3.43, 5.3-5.4).

The GA evaluates P individuals x C configurations per generation. Written per individual and
vmapped, every 3x3 product becomes a tiny batched matrix product; here the whole population is
one broadcast computation instead: a 3x3 matrix is a tuple of 9 arrays (structure of arrays) whose
entries broadcast over (configurations, individuals), so each product is plain elementwise
arithmetic that XLA fuses into a few loops. Constant parts stay small by broadcasting alone:
a parameter the GA does not vary is a scalar, a joint rotation is (C, 1), a module's PRY
rotation is (1, P); entries that are exactly 0 or 1 at trace time (principal rotations, the
identity base) are skipped. Chain (eq 3.43): R_k = R_{k-1} Rs_k Rm_k, p_k = p_{k-1} + R_k (b_k + bm_k).

Fitness (eq 5.4) compares the tip with the measurement mapped into the robot base frame,
T_meas = D Y M^-1 (D device frame, M marker): ||R_meas - R||_2 = sqrt(3 - tr(R_meas^T R)) (evaluated as
sqrt(|R_meas - R|_F^2 / 2), `jaxcal.ga.fitness`) and the
position distance are unchanged by that rigid map, so they equal the device-frame values.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from jaxcal.kin.joints.pry import PRY


def supports(robot, device) -> bool:
    """Whether the population path models this robot/device exactly (else use the vmapped path)."""
    serial = all(b.parent == i - 1 for i, b in enumerate(robot.bodies)) and robot.tip in (-1, len(robot.bodies) - 1)
    return (robot.closure is None and robot.gains is None and robot.coupling_joint is None and robot.coupling_motor is None
            and serial and all(b.conv is PRY and b.kind in PRY.kinds for b in robot.bodies)
            and device.marker_reading in ("point", "frame"))


# -- 3x3 algebra on tuples of broadcastable entries; Python floats 0.0 / 1.0 are folded at trace time --

def _mul(x, y):
    if isinstance(x, float) and x == 0.0 or isinstance(y, float) and y == 0.0:
        return 0.0
    if isinstance(x, float) and x == 1.0:
        return y
    if isinstance(y, float) and y == 1.0:
        return x
    return x * y


def _add(*terms):
    terms = [t for t in terms if not (isinstance(t, float) and t == 0.0)]
    if not terms:
        return 0.0
    out = terms[0]
    for t in terms[1:]:
        out = out + t
    return out


def mm(A, B):
    """A @ B for 3x3 matrices given as row tuples of entries."""
    return tuple(tuple(_add(*(_mul(A[i][k], B[k][j]) for k in range(3))) for j in range(3)) for i in range(3))


def mv(A, v):
    return tuple(_add(*(_mul(A[i][k], v[k]) for k in range(3))) for i in range(3))


def mt(A):
    return tuple(tuple(A[j][i] for j in range(3)) for i in range(3))


def rot_x(t):
    c, s = jnp.cos(t), jnp.sin(t)
    return ((1.0, 0.0, 0.0), (0.0, c, -s), (0.0, s, c))


def rot_y(t):
    c, s = jnp.cos(t), jnp.sin(t)
    return ((c, 0.0, s), (0.0, 1.0, 0.0), (-s, 0.0, c))


def rot_z(t):
    c, s = jnp.cos(t), jnp.sin(t)
    return ((c, -s, 0.0), (s, c, 0.0), (0.0, 0.0, 1.0))


IDENTITY = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


def exp_so3(w):
    """Rodrigues (as `jaxcal.kin.rotations.exp_so3`) for a rotation vector of 3 entries."""
    w1, w2, w3 = w
    t2 = w1 * w1 + w2 * w2 + w3 * w3
    small = t2 < 1e-12
    safe = jnp.where(small, 1.0, t2)
    th = jnp.sqrt(safe)
    a = jnp.where(small, 1.0 - t2 / 6.0, jnp.sin(th) / th)
    b = jnp.where(small, 0.5 - t2 / 24.0, (1.0 - jnp.cos(th)) / safe)
    K = ((0.0, -w3, w2), (w3, 0.0, -w1), (-w2, w1, 0.0))
    KK = mm(K, K)
    return tuple(tuple(_add(IDENTITY[i][j], a * K[i][j], b * KK[i][j]) for j in range(3)) for i in range(3))


def _constant_matrix(M):
    return tuple(tuple(float(x) for x in row) for row in np.asarray(M))


def pry_motion(kind, qv):
    """(Rm, bm) of seed 000 Table 3.3 (as `jaxcal.kin.conventions.pry_motion`)."""
    if kind == "revolute":
        return rot_z(qv[0]), (0.0, 0.0, 0.0)
    if kind == "prismatic":
        return IDENTITY, (0.0, 0.0, qv[0])
    if kind == "cylindrical":
        return rot_z(qv[0]), (0.0, 0.0, qv[1])
    if kind == "universal":
        return mm(rot_z(qv[0]), rot_y(qv[1])), (0.0, 0.0, 0.0)
    if kind == "spherical":
        return mm(mm(rot_z(qv[0]), rot_y(qv[1])), rot_x(qv[2])), (0.0, 0.0, 0.0)
    return IDENTITY, (0.0, 0.0, 0.0)  # fixed


def tip_pose(robot, param, q):
    """Tool frame (R, p) as entry tuples (C, P). param(j) gives parameter j (a scalar or (1, P));
    q (C, n_inputs) joint values, used as (C, 1) columns."""
    R = _constant_matrix(robot.base.R) if robot.base is not None else IDENTITY
    p = tuple(float(x) for x in np.asarray(robot.base.p)) if robot.base is not None else (0.0, 0.0, 0.0)
    for body in robot.bodies:
        row = [param(j) if j >= 0 else 0.0 for j in body.rows]
        Rs = mm(mm(rot_x(row[3]), rot_y(row[4])), rot_z(row[5]))  # entries (1, P) or scalars
        Rm, bm = pry_motion(body.kind, [q[:, i, None] for i in body.inputs])  # entries (C, 1)
        R = mm(mm(R, Rs), Rm)
        p = tuple(_add(p[i], v) for i, v in enumerate(mv(R, tuple(_add(row[i], bm[i]) for i in range(3)))))
    return R, p


def population_fitness(robot, device, a0, free_idx, pop, q, y, w1=1.0, w2=1.0):
    """Seed eq 5.3-5.4 for every individual of pop (..., n_free): a = a0 + dg on free_idx (static).

    a0: full robot + device vector; y: (C, 4, 4) pose or (C, 3) position readings. Returns (...)."""
    lead = pop.shape[:-1]
    flat = pop.reshape(-1, pop.shape[-1])
    where = {j: k for k, j in enumerate(free_idx)}

    def param(j):
        return a0[j] + flat[None, :, where[j]] if j in where else a0[j]

    R, p = tip_pose(robot, param, q)
    nr = robot.n_params
    dev = [param(nr + k) for k in range(device.n_params)]
    DR, Dp = exp_so3(dev[3:6]), tuple(dev[0:3])
    if device.marker_reading == "point":
        marker = mv(R, tuple(dev[6:9]))
        tip = tuple(_add(p[i], marker[i]) for i in range(3))
        target = tuple(_add(Dp[i], v) for i, v in enumerate(mv(DR, tuple(y[:, i, None] for i in range(3)))))
        cost = w1 * _norm3(tip, target)
    else:
        MR, Mp = exp_so3(dev[9:12]), tuple(dev[6:9])
        Yr = tuple(tuple(y[:, i, j, None] for j in range(3)) for i in range(3))
        Yp = tuple(y[:, i, 3, None] for i in range(3))
        # T_meas = D Y M^-1 compared with the tip T = (R, p): position R Mp + p vs D (Yp) and
        # rotations DR Yr and R MR (= (D Y M^-1)_R and R, the same spectral distance): sqrt(|A - B|_F^2 / 2)
        tip = tuple(_add(p[i], v) for i, v in enumerate(mv(R, Mp)))
        target = tuple(_add(Dp[i], v) for i, v in enumerate(mv(DR, Yp)))
        A, B = mm(DR, Yr), mm(R, MR)
        d = [A[i][j] - B[i][j] for i in range(3) for j in range(3)]
        cost = w1 * _norm3(tip, target) + w2 * jnp.sqrt(0.5 * _add(*(_mul(e, e) for e in d)))
    return jnp.sum(jnp.broadcast_to(cost, (q.shape[0], flat.shape[0])), axis=0).reshape(lead)


def _norm3(u, v):
    d = [u[i] - v[i] for i in range(3)]
    return jnp.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
