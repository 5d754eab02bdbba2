"""The hexapod (Gough-Stewart platform) builder, checked against the analytic inverse kinematics
l_i = |p + R b_i - a_i|: the MCPC tree closes on it, `jc.forward` recovers the platform pose from the leg
lengths, derivatives through the closure match finite differences, the identifiable count (42 geometric
numbers, 30 with the device frame and marker offset unknown), and a simulated full-pose calibration."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import central_fd, rel_err

import jaxcal as jc
from jaxcal.closure import core
from jaxcal.closure.track import value_and_jacobian
from jaxcal.robots.hexapod import hexapod_from_radii, hexapod_robot, leg_lengths, rigid_coordinates

RB, RP, GAP_B, GAP_P, HEIGHT = 0.5, 0.3, 0.35, 0.35, 0.6  # m, rad: a desktop-size symmetric hexapod
K = 12  # samples of the fast closure check (one shape: one compile)
STEPS = 8  # Newton steps of the hand closure (it converges in 4-5 from the home start)
HOME = (np.eye(3), np.array([0.0, 0.0, HEIGHT]))


@pytest.fixture(scope="module")
def rb():
    return hexapod_from_radii(RB, RP, GAP_B, GAP_P, HEIGHT)


def _points(rb, part, a=None):
    """(6, 3) joint centres legi_<part>.d1..d3 of parameters a (default nominal)."""
    a = np.asarray(rb.nominal_np if a is None else a)
    return np.array([[a[rb.index(f"leg{i + 1}_{part}.d{k + 1}")] for k in range(3)] for i in range(6)])


def _rotation(w):
    """Rodrigues: exp([w]x) for rotation vectors w (n, 3)."""
    t = np.linalg.norm(w, axis=1)[:, None, None]
    K_ = np.zeros((len(w), 3, 3))
    K_[:, 0, 1], K_[:, 0, 2], K_[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    K_ = (K_ - np.swapaxes(K_, 1, 2)) / np.where(t > 0, t, 1.0)
    return np.eye(3) + np.sin(t) * K_ + (1 - np.cos(t)) * K_ @ K_


def random_poses(n, seed, shift, tilt):
    """n platform poses around home: rotation vectors of random direction and angle <= tilt (rad), origin
    moved by up to shift (m) along each axis."""
    rng = np.random.default_rng(seed)
    w = rng.normal(size=(n, 3))
    w *= tilt * rng.uniform(0, 1, (n, 1)) / np.linalg.norm(w, axis=1, keepdims=True)
    return _rotation(w), HOME[1] + rng.uniform(-shift, shift, (n, 3))


def analytic_lengths(base, platform, R, p):
    """Inverse kinematics of a Stewart platform, written here independently of the builder."""
    return np.array([[np.linalg.norm(pk + Rk @ platform[i] - base[i]) for i in range(6)] for Rk, pk in zip(R, p)])


def _angle(R1, R2):
    """Angles (rad) of R1 R2^T, from its skew part (sin of the angle: exact for small angles; the trace
    rules out a half turn)."""
    M = R1 @ np.swapaxes(R2, -1, -2)
    w = np.stack([M[..., 2, 1] - M[..., 1, 2], M[..., 0, 2] - M[..., 2, 0], M[..., 1, 0] - M[..., 0, 1]], axis=-1)
    return np.where(np.trace(M, axis1=-2, axis2=-1) > 1.0, np.arcsin(np.minimum(np.linalg.norm(w, axis=-1) / 2, 1.0)), np.pi)


def _vee(M):
    return jnp.stack([M[2, 1], M[0, 2], M[1, 0]])


def _tree(rb, a, qi, th):
    """(closure residual, tool p, tool R) of the open tree from one evaluation of its frames: every closure pair
    of the hexapod is a ball joint, v = stacked p_slide - p_ball."""
    f = core.tree_frames(rb, a, qi, th)
    v = jnp.concatenate([f.p[i - 1] - f.p[j - 1] for i, j, _ in rb.closure.pairs])
    return v, f.p[rb.tip], f.R[rb.tip]


@functools.partial(jax.jit, static_argnums=0)
def _closed_by_hand(rb, a, q):
    """Per sample: the free joints by STEPS plain Newton steps on the square closure (18 x 18) from the home start, the tool
    (R, p), the closure residual, and the closed-loop Jacobian of the tool (position; rotation vector) by the
    implicit function theorem (seed 004 eq 2.69): d theta / d a = -V^-1 dv/da, J = T_a + T_theta d theta / d a."""
    n = a.shape[0]

    def one(qi):
        def newton(th, _):  # one pass gives the residual and tool and their Jacobians w.r.t. (a, theta)
            out = value_and_jacobian(lambda x: _tree(rb, x[:n], qi, x[n:]), jnp.concatenate([a, th]))
            return th - jnp.linalg.solve(out[1][0][:, n:], out[0][0]), out

        th, outs = jax.lax.scan(newton, jnp.zeros(rb.closure.n_free), None, length=STEPS)
        (v, p, R), (dv, dp, dR) = jax.tree_util.tree_map(lambda x: x[-1], outs)  # at the last (converged) iterate
        dw = jax.vmap(lambda M: _vee(M @ R.T), in_axes=2, out_axes=1)(dR)
        dth = -jnp.linalg.solve(dv[:, n:], dv[:, :n])
        J = jnp.concatenate([dp[:, :n] + dp[:, n:] @ dth, dw[:, :n] + dw[:, n:] @ dth])
        return R, p, jnp.linalg.norm(v), th, J

    return jax.vmap(one)(q)


@pytest.fixture(scope="module")
def by_hand(rb):
    """Home plus K - 1 random poses (5 cm, 15 degrees), their analytic leg lengths and the hand-closed tree."""
    R, p = random_poses(K - 1, seed=3, shift=0.05, tilt=np.radians(15))
    R, p = np.concatenate([HOME[0][None], R]), np.concatenate([HOME[1][None], p])
    q = analytic_lengths(_points(rb, "base"), _points(rb, "ball"), R, p)
    return R, p, q, [np.asarray(x) for x in _closed_by_hand(rb, rb.nominal, jnp.asarray(q))]


# -- fast: the model -------------------------------------------------------------------------------------------------
def test_layout_and_default_parameters(rb):
    """Symmetric layout (radii, 120-degree pairs, heights), home lengths from the analytic inverse kinematics, leg
    inputs, 30 free parameters (42 geometric numbers less the 12 rigid-motion coordinates), no-effect chain fixed."""
    a, b = _points(rb, "base"), _points(rb, "ball")
    assert np.allclose(np.linalg.norm(a[:, :2], axis=1), RB) and np.allclose(a[:, 2], 0)
    assert np.allclose(np.linalg.norm(b[:, :2], axis=1), RP) and np.allclose(b[:, 2], 0)
    ang = lambda x: np.degrees(np.arctan2(x[:, 1], x[:, 0]))  # noqa: E731
    assert np.allclose(np.diff(ang(a)[::2]) % 360, 120) and np.allclose(np.diff(ang(b)[1::2]) % 360, 120)
    assert np.allclose(rb.home_np, analytic_lengths(a, b, HOME[0][None], HOME[1][None])[0], atol=1e-12)
    assert rb.joint_names == tuple(f"leg{i}" for i in range(1, 7)) and rb.n_inputs == 6
    assert np.all(rb.q_min < rb.home_np) and np.all(rb.home_np < rb.q_max)
    free = [n for n, f in zip(rb.names, rb.free_mask) if f]
    assert len(free) == 30 and all(f"leg{i}_slide.d3" in free for i in range(1, 7))
    assert not any(n.startswith(("float", "platform")) for n in free)
    assert rb.closure.n_free == 18 and len(rb.closure.pairs) == 6
    assert all(kind == "position" for _, _, kind in rb.closure.pairs)
    for pts in (a, b):  # the fixed coordinates pin every rigid motion v + w x x_i
        G = np.concatenate([np.tile(np.eye(3), (6, 1)), -np.concatenate([np.cross(np.eye(3), x) for x in pts])], axis=1)
        assert np.linalg.matrix_rank(G[rigid_coordinates(pts)]) == 6
    assert np.allclose(leg_lengths(a, b, HOME[0], HOME[1]), rb.home_np, atol=1e-15)


def test_tree_closes_on_the_analytic_inverse_kinematics(rb, by_hand):
    """Newton on the MCPC closure from the home start, at the analytic leg lengths of random poses, closes
    (|v| < 1e-12) with the platform at the pose (1e-9 m, 1e-9 rad); at home it starts closed (every free joint 0)."""
    R, p, _, (Rt, pt, v, th, _) = by_hand
    assert np.max(v) < 1e-12, v
    dp = np.linalg.norm(pt - p, axis=1)
    dR = _angle(Rt, R)
    assert np.max(dp) < 1e-9 and np.max(dR) < 1e-9, (dp, dR)
    assert np.max(np.abs(th[0])) < 1e-12


def test_identifiable_count(rb, by_hand):
    """QR rank of the closed-loop Jacobian (implicit function theorem) over the K poses: the 42 geometric numbers
    (base points, platform points, leg offsets) are all identifiable with the base and tool frames known; with a
    full-pose device whose frame D and marker M are unknown (12 twist columns, y = D^-1 T M) they lose 12, and
    the default 30 free parameters with D and M are of full rank 42."""
    _, _, _, (Rt, pt, _, _, J) = by_hand
    J = np.concatenate(J)  # (6K, n_params)
    geometric = [i for i, n in enumerate(rb.names) if n.endswith(("base.d1", "base.d2", "base.d3", "ball.d1", "ball.d2",
                                                                     "ball.d3", "slide.d3"))]
    free = np.flatnonzero(rb.free_mask)
    frames = np.concatenate([np.block([[-np.eye(3), np.cross(np.eye(3), pk), Rk, np.zeros((3, 3))],
                                       [np.zeros((3, 3)), -np.eye(3), np.zeros((3, 3)), Rk]]) for Rk, pk in zip(Rt, pt)])
    rank = lambda M: np.linalg.matrix_rank(M / np.maximum(np.linalg.norm(M, axis=0), 1e-9), tol=1e-9)  # noqa: E731
    assert len(geometric) == 42 and rank(J[:, geometric]) == 42
    assert rank(np.concatenate([J[:, geometric], frames], axis=1)) == 42
    assert rank(np.concatenate([J[:, free], frames], axis=1)) == 42
    # with an effect: the joint centres (base/ball d and the a1 a2 that turn them, u1 d1 d2 and u2 d2 that move the
    # universal joint's centre), the leg offsets and u2.d1 (the distance between the universal joint's axes)
    effect = {n.partition("_")[2] for n, c in zip(rb.names, np.linalg.norm(J, axis=0)) if c > 1e-9}
    assert effect == {"base.a1", "base.a2", "base.d1", "base.d2", "base.d3", "u1.d1", "u1.d2", "u2.d1", "u2.d2",
                      "slide.d3", "ball.a1", "ball.a2", "ball.d1", "ball.d2", "ball.d3"}, effect
    assert rank(J[:, np.linalg.norm(J, axis=0) > 1e-9]) == 48  # the 42 and the six axis offsets u2.d1


def test_bad_input():
    a = _points(hexapod_from_radii(RB, RP, GAP_B, GAP_P, HEIGHT), "base")
    b = _points(hexapod_from_radii(RB, RP, GAP_B, GAP_P, HEIGHT), "ball")
    with pytest.raises(ValueError, match="shape"):
        hexapod_robot(a[:5], b, home_pose=HOME)
    with pytest.raises(ValueError, match="finite"):
        hexapod_robot(np.where(np.eye(6, 3) > 0, np.nan, a), b, home_pose=HOME)
    line = np.stack([np.linspace(-1, 1, 6), np.zeros(6), np.zeros(6)], axis=1)
    with pytest.raises(ValueError, match="base_points are collinear"):
        hexapod_robot(line, b, home_pose=HOME)
    with pytest.raises(ValueError, match="platform_points are collinear"):
        hexapod_robot(a, 0.1 * line, home_pose=HOME)
    with pytest.raises(ValueError, match="singular"):  # vertical legs: the platform slides sideways freely
        hexapod_robot(a, a, home_pose=HOME)
    with pytest.raises(ValueError, match="zero length"):
        hexapod_robot(a, a, home_pose=(np.eye(3), np.zeros(3)))
    with pytest.raises(ValueError, match=r"exclude the home pose \(leg 1: 0.6"):
        hexapod_robot(a, b, home_pose=HOME, stroke=(0.7, 0.9))
    with pytest.raises(ValueError, match="0 < shortest < longest"):
        hexapod_robot(a, b, home_pose=HOME, stroke=(0.9, 0.7))
    with pytest.raises(ValueError, match=r"\(shortest, longest\)"):
        hexapod_robot(a, b, home_pose=HOME, stroke=0.9)
    with pytest.raises(ValueError, match="numbers or 6 each"):
        hexapod_robot(a, b, home_pose=HOME, stroke=(0.5, [0.9] * 5))
    with pytest.raises(ValueError, match="not a rotation"):
        hexapod_robot(a, b, home_pose=(2 * np.eye(3), HOME[1]))
    with pytest.raises(ValueError, match="4x4"):
        hexapod_robot(a, b, home_pose=np.eye(3))
    with pytest.raises(ValueError, match="rb must be a positive"):
        hexapod_from_radii(-RB, RP, GAP_B, GAP_P, HEIGHT)
    tool = np.eye(4)
    tool[2, 3] = 0.1
    rt = hexapod_robot(a, b, home_pose=HOME, tool=tool, stroke=(0.5, 0.9))
    assert rt.bodies[rt.tip].name == "tool" and np.allclose(rt.q_min, 0.5)


# -- slow: the closure through jc.forward, derivatives, calibration --------------------------------------------------
N = K  # one batch shape for jc.forward: the finite differences below reuse its compiled closure


@pytest.mark.slow  # compiles the generic closure of a 37-body tree: 24-63 s on the shared 2-core machine
def test_forward_recovers_the_pose(rb):
    """jc.forward at the analytic leg lengths of random poses (4 cm, 10 degrees) lands on the pose to 1e-9 m and
    1e-9 rad (the assembly mode of home); over a wider workspace (10 cm, 25 degrees) every sample is either closed
    on the pose or flagged by the closure status (never a silent wrong pose)."""
    base, platform = _points(rb, "base"), _points(rb, "ball")
    for shift, tilt, must_close in ((0.04, np.radians(10), True), (0.10, np.radians(25), False)):
        R, p = random_poses(N, seed=7, shift=shift, tilt=tilt)
        q = analytic_lengths(base, platform, R, p)
        pose = jc.forward(rb, rb.nominal, q)
        dp = np.linalg.norm(np.asarray(pose.p) - p, axis=1)
        dR = _angle(np.asarray(pose.R), R)
        right = (dp < 1e-9) & (dR < 1e-9)
        status = np.asarray(jc.closure.closure_status(rb, rb.nominal, q)) if not right.all() else np.zeros(N, int)
        msg = f"shift {shift} m tilt {np.degrees(tilt):.0f} deg: {right.mean():.0%} closed, status {status.tolist()}"
        print(msg, f"max errors {dp.max():.2e} m {dR.max():.2e} rad")
        assert right.all() or not must_close, msg
        assert np.all(right == (status == jc.closure.CLOSED)), msg
        assert right.mean() >= 0.75, msg


@pytest.mark.slow  # compiles jacfwd through the closure: 43-141 s
def test_jacobian_through_closure_matches_finite_differences(rb, by_hand):
    """jax.jacfwd of jc.forward (position; rotation vector) w.r.t. the free parameters against central finite
    differences, and against the implicit-function-theorem Jacobian of the hand-closed tree."""
    _, _, q, (_, _, _, _, J_ift) = by_hand
    free = np.flatnonzero(rb.free_mask)
    q = jnp.asarray(q)
    R0 = jc.forward(rb, rb.nominal, q).R

    def pose(x):
        f = jc.forward(rb, rb.nominal.at[free].set(x), q)
        w = jax.vmap(jc.kin.rotations.log_so3)(f.R @ jnp.swapaxes(R0, 1, 2))
        return jnp.concatenate([f.p, w], axis=1)

    x0 = rb.nominal_np[free]
    J = np.asarray(jax.jacfwd(pose)(jnp.asarray(x0))).reshape(K, 6, -1)
    J_fd = central_fd(lambda x: np.asarray(pose(jnp.asarray(x))), x0, h=1e-6).reshape(K, 6, -1)
    err, err_ift = rel_err(J, J_fd), rel_err(J, J_ift[:, :, free])
    print(f"jacfwd vs central FD {err:.2e}, vs implicit function theorem {err_ift:.2e}")
    assert err < 1e-6 and err_ift < 1e-9, f"relative error vs central FD {err:.2e}, vs implicit function theorem {err_ift:.2e}"


@pytest.mark.slow  # simulated calibration through the closure: 228-334 s
def test_full_pose_calibration(rb):
    """Simulated calibration with a full-pose device (frame and marker unknown, identified with the robot): free
    parameters perturbed by ~1 mm, 40 poses, noise-free. All 30 + 12 parameters are estimated (none regrouped) and
    the predicted readings at 20 new poses (4x4 frames in the device frame, here the base frame) are the true poses
    to 0.01 mm and 1e-7 rad."""
    a_true = jc.perturb(rb, scale={"length": 1e-3}, seed=2)
    fit_R, fit_p = random_poses(40, seed=11, shift=0.05, tilt=np.radians(12))
    new_R, new_p = random_poses(20, seed=12, shift=0.05, tilt=np.radians(12))
    base, platform = _points(rb, "base", a_true), _points(rb, "ball", a_true)
    offsets = np.array([a_true[rb.index(f"leg{i}_slide.d3")] for i in range(1, 7)])  # the slide sits at q + d3
    data = jc.simulate(rb, a_true, analytic_lengths(base, platform, fit_R, fit_p) - offsets, device="pose")
    fit = jc.identify(rb, data)
    pred = np.asarray(fit.predict(analytic_lengths(base, platform, new_R, new_p) - offsets))
    dp, dR = np.linalg.norm(pred[:, :3, 3] - new_p, axis=1), _angle(pred[:, :3, :3], new_R)
    print(f"rms before {fit.rms_before:.3e} after {fit.rms_after:.3e} mm, held-out max {dp.max() * 1e3:.2e} mm "
          f"{dR.max():.2e} rad, estimated {len(fit.estimated)}, timings {fit.timings}")
    assert len(fit.estimated) == 42 and not fit.regrouped and not fit.undetermined, (fit.estimated, fit.regrouped)
    assert dp.max() < 1e-5 and dR.max() < 1e-7, (dp, dR)
