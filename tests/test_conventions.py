"""The joint-convention interface: derivatives of every registered convention, the Table 3.3 joint
kinds by hand (seed 000), and a convention added in this file (standard DH) driving `jc.forward`."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import central_fd, rel_err

import jaxcal as jc
from jaxcal.kin import Body, Pose, Robot
from jaxcal.kin.convention import Convention, get_convention, register, registered
from jaxcal.kin.rotations import rot_x, rot_z

FD_BOUND = 1e-7  # central differences with h = 1e-6 in float64: truncation ~1e-12, rounding ~1e-10
CASES = [(name, kind) for name in registered() for kind in get_convention(name).kinds]


def _sizes(conv, kind):
    """Row and joint-value lengths local_transform takes (doubled when it also reads the parent's)."""
    k = 2 if conv.reads_parent else 1
    return k * len(conv.row_names), k * conv.n_inputs(kind)


def _flat(pose):
    return jnp.concatenate([pose.R.reshape(-1), pose.p])


def _sample(conv, kind, seed):
    rng = np.random.default_rng(seed)
    n_row, n_q = _sizes(conv, kind)
    return rng.uniform(-0.8, 0.8, n_row), rng.uniform(-0.8, 0.8, n_q)


@pytest.mark.parametrize("name,kind", CASES, ids=[f"{n}-{k}" for n, k in CASES])
def test_local_transform_jacobians_match_finite_differences(name, kind):
    conv = get_convention(name)
    row, qv = _sample(conv, kind, 7)
    f_row = jax.jit(lambda r: _flat(conv.local_transform(jnp.asarray(r), kind, jnp.asarray(qv))))  # compiled whole
    err = rel_err(jax.jacfwd(f_row)(jnp.asarray(row)), central_fd(f_row, row))
    assert err < FD_BOUND, f"{name} {kind}: d/d row relative error {err:.2e} >= {FD_BOUND:.0e}"
    if qv.size:
        f_q = jax.jit(lambda q: _flat(conv.local_transform(jnp.asarray(row), kind, jnp.asarray(q))))  # compiled whole
        err = rel_err(jax.jacfwd(f_q)(jnp.asarray(qv)), central_fd(f_q, qv))
        assert err < FD_BOUND, f"{name} {kind}: d/d qv relative error {err:.2e} >= {FD_BOUND:.0e}"


@pytest.mark.parametrize("name,kind", CASES, ids=[f"{n}-{k}" for n, k in CASES])
def test_joint_queries_agree_with_the_transform(name, kind):
    """The first joint variable adds to row[joint_row_index]; a one-input joint moves along or about
    joint_axis (body frame, or the parent's when axis_in_parent_frame), about a point on the axis that is the parent's
    or the body's origin."""
    conv = get_convention(name)
    row, qv = _sample(conv, kind, 11)
    assert conv.is_fixed(kind) == (conv.n_inputs(kind) == 0)
    assert not (conv.is_prismatic(kind) and conv.is_revolute(kind))
    if conv.is_fixed(kind):
        assert conv.joint_row_index(kind) is None
        return
    own = conv.n_inputs(kind) if conv.reads_parent else 0  # the body's own values follow the parent's
    idx = conv.joint_row_index(kind) + (len(conv.row_names) if conv.reads_parent else 0)
    step = 0.3
    moved_q = conv.local_transform(row, kind, qv.copy() + step * (np.arange(qv.size) == own))
    moved_row = conv.local_transform(row + step * (np.arange(row.size) == idx), kind, qv)
    np.testing.assert_allclose(_flat(moved_q), _flat(moved_row), atol=1e-12)
    if conv.n_inputs(kind) != 1:
        return
    T = lambda s: conv.local_transform(row, kind, qv + s * (np.arange(qv.size) == own))  # noqa: E731
    dR, dp = jax.jacfwd(lambda s: tuple(T(s)))(0.0)
    R, p = (np.asarray(x) for x in T(0.0))
    axis = conv.joint_axis(kind)
    assert abs(np.linalg.norm(axis) - 1.0) < 1e-12
    if conv.is_prismatic(kind):
        np.testing.assert_allclose(dR, 0.0, atol=1e-12)
        np.testing.assert_allclose(dp if conv.axis_in_parent_frame(kind) else R.T @ dp, axis, atol=1e-12)
    else:
        w = axis if conv.axis_in_parent_frame(kind) else R @ axis  # the axis in the parent's frame
        skew = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
        np.testing.assert_allclose(dR, skew @ R, atol=1e-12)
        centre = np.zeros(3) if conv.axis_through_parent_origin(kind) else p
        np.testing.assert_allclose(dp, np.cross(w, p - centre), atol=1e-12)


def test_registry_rejects_unknown_names():
    with pytest.raises(ValueError, match="unknown convention"):
        get_convention("no-such-convention")
    assert {"pry", "mdh", "mcpc", "urdf", "planar"} <= set(registered())


# -- Table 3.3 by hand (seed 000): Rs = Rx(pitch) Ry(roll) Rz(yaw), T = (Rs Rm, Rs Rm (bs + bm)) --

def _rx(t):
    c, s = np.cos(t), np.sin(t)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _ry(t):
    c, s = np.cos(t), np.sin(t)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rz(t):
    c, s = np.cos(t), np.sin(t)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


ROW = np.array([0.12, -0.05, 0.3, 0.2, -0.35, 0.7])
MOTION = {  # kind: (joint values, Rm, bm) written out from Table 3.3
    "cylindrical": ((0.4, 0.25), _rz(0.4), np.array([0.0, 0.0, 0.25])),
    "universal": ((0.4, -0.6), _rz(0.4) @ _ry(-0.6), np.zeros(3)),
    "spherical": ((0.4, -0.6, 1.1), _rz(0.4) @ _ry(-0.6) @ _rx(1.1), np.zeros(3)),
}


@pytest.mark.parametrize("kind", sorted(MOTION))
def test_pry_table_3_3_kinds_by_hand(kind):
    qv, Rm, bm = MOTION[kind]
    Rs = _rx(ROW[3]) @ _ry(ROW[4]) @ _rz(ROW[5])
    R_hand = Rs @ Rm
    p_hand = R_hand @ (ROW[:3] + bm)
    pose = get_convention("pry").local_transform(jnp.asarray(ROW), kind, jnp.asarray(qv))
    np.testing.assert_allclose(np.asarray(pose.R), R_hand, rtol=0, atol=1e-14)
    np.testing.assert_allclose(np.asarray(pose.p), p_hand, rtol=0, atol=1e-14)


# -- adding a convention in one place: standard (distal) DH, defined and registered here --

class StandardDH(Convention):
    """T = Rz(theta) Tz(d) Tx(a) Rx(alpha); kind 0: the joint adds to theta, kind 1: to d.

    The joint moves along the parent's z axis, which in this body's frame is Rx(alpha)^T z and so
    depends on the row; joint_axis is not overridden, so this example serves forward kinematics only.
    """

    name = "test-standard-dh"
    row_names = ("theta", "d", "a", "alpha")
    kinds = (0, 1)

    def local_transform(self, row, kind, qv) -> Pose:
        theta, d, a, alpha = row
        theta, d = (theta + qv[0], d) if kind == 0 else (theta, d + qv[0])
        p = jnp.stack([a * jnp.cos(theta), a * jnp.sin(theta), d])
        return Pose(rot_z(theta) @ rot_x(alpha), p)

    def n_inputs(self, kind) -> int:
        return 1

    def is_prismatic(self, kind) -> bool:
        return kind == 1

    def joint_row_index(self, kind) -> int | None:
        return kind

    def axis_through_parent_origin(self, kind) -> bool:
        return True


def _dh_matrix(theta, d, a, alpha):
    rz, rx = np.eye(4), np.eye(4)
    rz[:3, :3], rx[:3, :3] = _rz(theta), _rx(alpha)
    tz, tx = np.eye(4), np.eye(4)
    tz[2, 3], tx[0, 3] = d, a
    return rz @ tz @ tx @ rx


def test_a_convention_defined_here_drives_forward():
    register(StandardDH())
    rows = np.array([[0.1, 0.4, 0.3, np.pi / 2], [-0.2, 0.05, 0.25, 0.0], [0.3, 0.1, 0.0, -np.pi / 2]])
    kinds = (0, 0, 1)
    bodies = tuple(Body(f"j{i + 1}", StandardDH.name, kinds[i], i - 1, tuple(range(4 * i, 4 * i + 4)), (i,))
                   for i in range(3))
    names = tuple(f"j{i + 1}.{f}" for i in range(3) for f in StandardDH.row_names)
    arm = Robot(name="dh3", bodies=bodies, names=names, nominal_np=rows.reshape(-1),
                units=("angle", "length", "length", "angle") * 3, free_mask=np.ones(12, bool), priority=np.ones(12),
                joint_names=("j1", "j2", "j3"), home_np=np.zeros(3), q_min=-np.ones(3), q_max=np.ones(3))
    q = np.array([0.7, -0.45, 0.12])
    T = np.eye(4)
    for (theta, d, a, alpha), kind, qi in zip(rows, kinds, q):
        T = T @ (_dh_matrix(theta + qi, d, a, alpha) if kind == 0 else _dh_matrix(theta, d + qi, a, alpha))
    pose = jc.forward(arm, arm.nominal, q)
    np.testing.assert_allclose(np.asarray(pose.R), T[:3, :3], atol=1e-14)
    np.testing.assert_allclose(np.asarray(pose.p), T[:3, 3], atol=1e-14)
    assert hash(arm.bodies[0]) == hash(Body("j1", StandardDH.name, 0, -1, (0, 1, 2, 3), (0,)))


@pytest.mark.parametrize("name,kind", CASES, ids=[f"{n}-{k}" for n, k in CASES])
def test_motion_split_reproduces_the_transform(name, kind):
    """T(row, kind, q) = A M(q) B for the (A, B) of motion_split (used to write URDF), M the motion about
    or along joint_axis; conventions that cannot be split say so (NotImplementedError)."""
    conv = get_convention(name)
    if conv.reads_parent or conv.n_inputs(kind) > 1:
        pytest.skip("absolute angles / several joint variables: no one-joint URDF split")
    row, qv = _sample(conv, kind, 13)
    try:
        A, B = conv.motion_split(row, kind)
    except NotImplementedError:
        pytest.skip(f"{name} does not split")
    M = np.eye(4)
    if conv.n_inputs(kind) == 1:
        u = conv.joint_axis(kind)
        if conv.is_prismatic(kind):
            M[:3, 3] = u * qv[0]
        else:
            K = np.array([[0.0, -u[2], u[1]], [u[2], 0.0, -u[0]], [-u[1], u[0], 0.0]])
            M[:3, :3] = np.eye(3) + np.sin(qv[0]) * K + (1 - np.cos(qv[0])) * K @ K
    T = np.asarray(conv.local_transform(jnp.asarray(row), kind, jnp.asarray(qv)).matrix())
    np.testing.assert_allclose(A @ M @ B, T, atol=1e-14)
