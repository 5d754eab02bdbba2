"""The Kiwibot's nominal geometry (seed 004 ch. 1, §4.2, §4.3, Table 4.4): homokinetic direct and
inverse solutions, and the closure start they give the Table 4.4 model.

The Kiwibot is Hunt's constant-velocity coupling made into a robot: the upper half (nacelle and
passive arms) is the mirror image of the lower half (base and actuated arms) in the homokinetic
plane through the three ball-joint centres E_i. With n the unit normal of that plane (pointing away
from the base) and d its distance from the base centre, the reflection M = I - 2 n n^T maps base
joint B_i to nacelle joint N_i = M B_i + 2 d n. The nacelle frame 10 of Table 4.4 holds its joints at
-B_i (d1 = -0.2805 against the base's +0.2805), so

    p_10 = 2 d n,    R_10 = -M = 2 n n^T - I   (a half turn about n),

and the nacelle axis z_10 = 2 (n . z) n - z turns twice as far as the plane: the two rotational
freedoms and the "plunging" freedom (strut length |p_10| = 2 d) of seed 004 ch. 1.

Assembly mode. The tree of Table 4.4 also closes with each passive arm folded back onto its actuated
arm and the nacelle inside the base (p_10 = 0 for every actuator setting). There the simulated ball
joint 6-7-8 (x-z-x Euler angles about the arm) is in gimbal lock (theta_7 = 0) and the closure
Jacobian dv/dtheta is singular. `closure_start` starts every closure from the mirror mode above, in
which theta_7 = -2 beta_1 (beta_1: angle between arm 1 and the homokinetic plane), far from 0 and
from pi over the actuator range and over the hemisphere of pointing directions.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.kin.pose import Pose
from jaxcal.kin.rotations import log_so3, rot_x, rot_y, rot_z

BASE_RADIUS = 0.2805  # m, Table 4.4 rows 2-4 and 11-12 (d1)
ARM = 0.6  # m, actuated (rows 5, 13, 14) and passive (rows 9, 15, 16) arm lengths
PSI = (0.0, 2.0 * np.pi / 3.0, -2.0 * np.pi / 3.0)  # azimuth of actuators 2, 3, 4 (Table 4.4 a2)
HOME_STRUT = 2.0 * ARM * np.sin(0.5)  # |p_10| at the home setting theta = (0.5, 0.5, 0.5)
# Strut length of the simulation grid: at 0.7 m the whole hemisphere of pointing directions is reachable
# and cond(dv/dtheta) stays below ~50; at the home strut (0.575 m) it reaches ~400 at 80 degrees of tilt.
STUDY_STRUT = 0.7
FREE = (6, 7, 8, 9, 11, 12)  # free joints of the Table 4.4 closure, in the order of theta_free


def _radial():
    psi = jnp.asarray(PSI)
    return jnp.stack([jnp.cos(psi), jnp.sin(psi), jnp.zeros(3)], axis=1)


def base_joints():
    """B_i: the actuated joint centres (3, 3) in the base frame."""
    return BASE_RADIUS * _radial()


def elbows(theta):
    """E_i = B_i + ARM (cos theta_i r_i + sin theta_i z): the ball-joint centres (3, 3)."""
    theta = jnp.asarray(theta, dtype=jnp.float64)
    up = jnp.array([0.0, 0.0, 1.0])
    arm = jnp.cos(theta)[:, None] * _radial() + jnp.sin(theta)[:, None] * up
    return base_joints() + ARM * arm


def homokinetic_plane(theta):
    """(n, d): unit normal (n_z > 0) and distance from the base centre of the plane through E_1..E_3."""
    E = elbows(theta)
    n = jnp.cross(E[1] - E[0], E[2] - E[0])
    n = n / jnp.linalg.norm(n)
    n = jnp.where(n[2] < 0, -n, n)
    return n, jnp.dot(n, E[0])


def direct(theta) -> Pose:
    """Nominal direct solution: nacelle frame 10 (R = 2 n n^T - I, p = 2 d n) for actuator angles theta."""
    n, d = homokinetic_plane(theta)
    return Pose(2.0 * jnp.outer(n, n) - jnp.eye(3), 2.0 * d * n)


def inverse(pointing, strut=HOME_STRUT):
    """Nominal inverse solution: actuator angles (3,) that point the nacelle axis z_10 along `pointing`
    at strut length |p_10| = strut, and a feasibility flag.

    The plane normal is the bisector n = (z + k)/|z + k|, at distance strut/2; each elbow must lie in
    it: ARM (n . r_i) cos theta + ARM n_z sin theta = strut/2 - n . B_i, solved on the branch that
    gives theta = 0.5 at home.
    """
    k = jnp.asarray(pointing, dtype=jnp.float64)
    k = k / jnp.linalg.norm(k)
    n = jnp.array([0.0, 0.0, 1.0]) + k
    n = n / jnp.linalg.norm(n)
    A = ARM * (_radial() @ n)
    C = ARM * n[2]
    D = 0.5 * strut - base_joints() @ n
    ratio = D / jnp.hypot(A, C)
    ok = jnp.all(jnp.abs(ratio) <= 1.0)
    theta = jnp.arctan2(C, A) - jnp.arccos(jnp.clip(ratio, -1.0, 1.0))
    return theta, ok


def hemisphere_grid(n: int = 160, max_tilt: float = np.pi / 2, strut: float = STUDY_STRUT):
    """n actuator settings whose nacelle axes spread evenly (Fibonacci spiral) over the cap of
    pointing directions within max_tilt of vertical, at a constant strut length (seed 004 §4.3: "160
    positions approximately spanning a hemisphere"). Returns (theta (n, 3), pointing (n, 3))."""
    k = np.arange(n) + 0.5
    cos_tilt = 1.0 - (1.0 - np.cos(max_tilt)) * k / n
    azimuth = np.pi * (3.0 - np.sqrt(5.0)) * k
    sin_tilt = np.sqrt(1.0 - cos_tilt**2)
    pointing = np.stack([sin_tilt * np.cos(azimuth), sin_tilt * np.sin(azimuth), cos_tilt], axis=1)
    theta, ok = jax.vmap(lambda p: inverse(p, strut))(jnp.asarray(pointing))
    if not bool(jnp.all(ok)):
        raise ValueError(f"hemisphere_grid: {int(jnp.sum(~ok))} of {n} pointing directions out of reach at strut {strut} m")
    return np.asarray(theta), pointing


def _xzx_angles(M):
    """(a, b, c) with M = Rx(a) Rz(b) Rx(c), on the branch b <= 0 (the mirror mode's theta_7 < 0)."""
    sb = -jnp.hypot(M[1, 0], M[2, 0])
    return jnp.arctan2(-M[2, 0], -M[1, 0]), jnp.arctan2(sb, M[0, 0]), jnp.arctan2(-M[0, 2], M[0, 1])


def _nacelle_joint(R10, p10, psi, elbow):
    """Joint value of nacelle joint 11 or 12 (rows a1 = pi/2, a2 = psi, d1 = -BASE_RADIUS) whose arm
    (x axis, length ARM, Table 4.4 rows 15-16) reaches the elbow."""
    V = rot_x(jnp.pi / 2) @ rot_y(psi)
    p = p10 + R10 @ V @ jnp.array([-BASE_RADIUS, 0.0, 0.0])
    x = (V.T @ R10.T @ (p - elbow)) / ARM
    return jnp.arctan2(x[1], x[0])


def closure_start(a, qj):
    """theta_free (joints 6 7 8 9 11 12) of the nominal mirror-mode assembly for actuator joint values
    qj; `a` is unused (a start only needs to lie in the right basin)."""
    del a
    theta = jnp.asarray(qj, dtype=jnp.float64)
    R10, p10 = direct(theta)
    E = elbows(theta)
    # passive arm 9: from ball centre E_1 to nacelle joint N_1 = p10 - R10 (BASE_RADIUS, 0, 0) along -z_8
    p9 = p10 - R10 @ jnp.array([BASE_RADIUS, 0.0, 0.0])
    z8 = (E[0] - p9) / ARM
    w = rot_x(-jnp.pi / 2) @ R10.T @ z8
    q9 = jnp.arctan2(w[1], -w[0])
    R8 = R10 @ rot_x(jnp.pi / 2) @ rot_z(-q9) @ rot_y(-jnp.pi / 2)
    R5 = rot_x(jnp.pi / 2) @ rot_z(theta[0])  # frame 5 = frame 2 moved along its arm
    q6, q7, q8 = _xzx_angles(R5.T @ R8 @ rot_y(-jnp.pi / 2))
    q11 = _nacelle_joint(R10, p10, PSI[1], E[1])
    q12 = _nacelle_joint(R10, p10, PSI[2], E[2])
    return jnp.stack([q6, q7, q8, q9, q11, q12])


STRUT_WEIGHT = 1.0  # rad per m: 1 mm of strut-length change costs as much as 1 mrad of orientation error


def pointing_residual(pose: Pose, R_target, strut, weight=STRUT_WEIGHT):
    """Residual of the Kiwibot's orientation compensation with the strut-length bias (seed 004 §4.3):
    r = [log(R_target^T R_10); weight (|p_10| - strut)], (4,). The three actuators cannot set the
    nacelle's position and orientation at once; beam aiming needs the orientation, and since an
    orientation is reachable at any strut length the thesis adds a bias on the strut length (the
    distance from frame 1, the base centre at the origin, to frame 10) to keep the nacelle near its
    target distance. The weight is not printed; 1 rad/m treats metres and radians alike."""
    return jnp.concatenate([log_so3(R_target.T @ pose.R), weight * (jnp.linalg.norm(pose.p) - strut)[None]])


def with_kiwibot_closure(robot, solver: str = "newton"):
    """The Table 4.4 robot closing every sample from `closure_start` (mirror mode) with `solver`."""
    c = robot.closure
    if tuple(c.free) != FREE:
        raise ValueError(f"robot {robot.name!r}: expected the Table 4.4 free joints {FREE}, got {c.free}")
    return robot.replace(closure=dataclasses.replace(c, start_fn=closure_start, solver=solver))


# Table 4.5: (parameter, printed nominal, printed perturbed model, thesis' identified - perturbed for sims 1, 2, 3).
# The OCR shows a second "2, alpha1" row (1.5708, 1.5708) with no counterpart in Table 4.4: left out.
TABLE_4_5 = [
    ("j2.a1", 1.5708, 1.5708, -1.2e-11, 4e-10, 3.6e-6),
    ("j2.a2", 0.0, 0.00033725, 1.8e-10, 4.1e-6, 5.1e-6),
    ("j2.a3", 0.0, -4.6444e-5, 4.2e-10, 5.7e-6, 6.5e-5),
    ("j2.d1", 0.28054, 0.28046, 9.5e-11, -0.00017, -2.1e-5),
    ("j2.d2", 0.0, 7.7014e-5, -9.8e-11, 0.00014, 2.1e-5),
    ("j3.a1", 1.5708, 1.5706, -2.5e-8, 0.00024, 6.2e-5),
    ("j3.a2", 2.0944, 2.094, -8.6e-9, 4.8e-5, 4.4e-5),
    ("j3.a3", 0.0, 0.000257, -2.4e-8, -0.00018, 7.7e-5),
    ("j3.d1", 0.28054, 0.28069, -3.8e-10, 0.00012, -4.4e-5),
    ("j3.d2", 0.0, -6.2891e-5, 6.9e-9, 3.9e-6, -3.9e-5),
    ("j4.a1", 1.5708, 1.5707, -4.8e-8, -0.00019, -0.00013),
    ("j4.a2", -2.0944, -2.0946, -1.3e-8, -2.3e-5, 3.2e-5),
    ("j4.a3", 0.0, 0.0001152, -1e-8, -0.00018, -6.2e-5),
    ("j4.d1", 0.28054, 0.28087, -8.8e-10, 0.0001, -2.8e-5),
    ("j4.d2", 0.0, -0.00022635, -3.3e-9, 6.5e-5, 1.7e-5),
    ("j9.a1", 0.0, 0.00048966, -0.00049, -0.00049, -0.00049),
    ("j9.a2", 1.5708, 1.5709, -0.00013, -0.00013, -0.00013),
    ("j9.d1", 0.6, 0.59987, 4.6e-9, 1.7e-5, -1.5e-5),
    ("j9.d2", 0.0, -7.4756e-5, 7.5e-5, 7.5e-5, 1.9e-9),
    ("j11.a1", 1.5708, 1.5707, -2.9e-8, 0.00021, -2.2e-5),
    ("j11.a2", 2.0944, 2.0941, -1.1e-8, 3.7e-5, -4.2e-5),
    ("j11.d1", -0.28054, -0.28091, -5.4e-10, -3.3e-5, 6.7e-5),
    ("j11.d2", 0.0, -0.00046711, -8e-9, 0.00012, 4.2e-5),
    ("j12.a1", 1.5708, 1.5713, -5.3e-8, -0.00013, 0.00011),
    ("j12.a2", -2.0944, -2.094, -1.6e-8, 6.7e-6, 3.7e-5),
    ("j12.d1", -0.28054, -0.28014, 2.2e-9, -2.2e-5, 3e-5),
    ("j12.d2", 0.0, -0.00041224, 5e-9, 5.4e-5, -5.5e-5),
    ("j13.a1", 0.0, 0.0001265, -0.00013, -0.00013, -2.7e-8),
    ("j13.a2", 0.0, -0.00035271, 1.8e-8, 0.00012, 8.3e-7),
    ("j13.d1", 0.6, 0.59968, -2e-10, 8.5e-5, 7.8e-6),
    ("j14.a1", 0.0, 0.00010595, -0.00011, -0.00011, -2.2e-8),
    ("j14.a2", 0.0, 0.00035953, 3e-8, -0.00017, -9.7e-6),
    ("j14.d1", 0.6, 0.60005, -7.4e-9, 4.4e-5, -5e-5),
    ("j15.a1", 0.0, -0.00033905, 0.00034, 0.00034, 1.7e-11),
    ("j15.a2", 0.0, 0.00046351, 2.1e-8, -0.00013, 0.00011),
    ("j15.d1", -0.6, -0.59952, 9.2e-10, -7.4e-5, -1.5e-5),
    ("j16.a1", 0.0, -3.1958e-5, 3.2e-5, 3.2e-5, 6.2e-13),
    ("j16.a2", 0.0, -0.00040755, 3.4e-8, 6.1e-5, -4.7e-5),
    ("j16.d1", -0.6, -0.60004, None, 4.8e-5, 4.2e-5),  # sim 1 entry lost in the OCR
]
# Table 4.5 text (§4.3): residual norm before -> after of simulations 1-3.
THESIS_NORMS = {"sim1": (1.54e-2, 7.54e-10), "sim2": (1.23e-2, 1.19e-8), "sim3": (0.0124, 8.66e-4)}


def thesis_perturbed(rb):
    """Nominal (Table 4.4) plus the thesis' perturbation (Table 4.5 perturbed - nominal)."""
    a = np.array(rb.nominal_np)
    for name, nominal, perturbed, *_ in TABLE_4_5:
        a[rb.index(name)] += perturbed - nominal
    return jnp.asarray(a)
