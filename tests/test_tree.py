"""Trees read at several links (issue 19 item 2): a torso with two arms, a marker on each hand, read
together by one tracker. The shared torso is one set of parameters; each marker rides on its own tip."""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import central_fd, rel_err

import jaxcal as jc
from jaxcal.cli import main
from jaxcal.fit.identify import residual_weights, residuals
from jaxcal.gap.effects import gap_model
from jaxcal.gap.effects import residuals as gap_residuals
from jaxcal.gap.fit import covariate_matrix
from jaxcal.robots import twoarm
from jaxcal.robots.urdf import load_urdf

TIPS = list(twoarm.TIPS)
FRAME = np.array([1.4, -0.9, 0.5, 0.4, -0.7, 2.1])  # tracker 1.7 m away, turned 2.3 rad
MARKERS = np.array([0.03, 0.01, -0.04, -0.02, 0.05, -0.03])


@pytest.fixture(scope="module")
def urdf_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("tree") / "twoarm.urdf"
    path.write_text(twoarm.two_arm_urdf())
    return str(path)


@pytest.fixture(scope="module")
def tree(urdf_path):
    return load_urdf(urdf_path, base="base_link", tips=TIPS)


def test_each_tip_is_its_chain_and_shared_links_are_one_body(urdf_path, tree):
    left, right = (load_urdf(urdf_path, base="base_link", tip=t) for t in TIPS)
    assert tree.tips == (5, 9) and tree.n_tips == 2
    assert tree.joint_names == ("torso_yaw", "torso_pitch", "left_1", "left_2", "left_3", "right_1", "right_2", "right_3")
    assert tree.n_params == left.n_params + right.n_params - 14  # the torso joints' 2 x 7 parameters once
    assert [b.parent for b in tree.bodies] == [-1, 0, 1, 2, 3, 4, 1, 6, 7, 8]
    q = jc.random_configurations(tree, 6, seed=1)
    a = jc.perturb(tree, 5e-3, seed=2)
    both = jc.forward(tree, a, q)
    assert both.p.shape == (6, 2, 3) and both.R.shape == (6, 2, 3, 3)
    for k, chain in enumerate((left, right)):
        cols = [tree.joint_names.index(n) for n in chain.joint_names]
        a_chain = np.array([a[tree.index(n)] for n in chain.names])
        one = jc.forward(chain, a_chain, q[:, cols])
        assert np.abs(np.asarray(both.p[:, k]) - np.asarray(one.p)).max() < 1e-15
        assert np.abs(np.asarray(both.R[:, k]) - np.asarray(one.R)).max() < 1e-15
    builtin = jc.robots.get("twoarm")  # the built-in tree is this file's robot
    assert builtin.names == tree.names and builtin.tips == tree.tips
    assert np.abs(np.asarray(jc.forward(builtin, a, q).p) - np.asarray(both.p)).max() < 1e-15


def test_a_marker_twice_on_one_link_and_bad_requests(urdf_path):
    three = load_urdf(urdf_path, base="base_link", tips=["left_hand", "left_hand", "right_hand"])
    assert three.tips == (5, 5, 9)
    two = load_urdf(urdf_path, base="base_link", tips=TIPS)
    with pytest.raises(ValueError, match=r"multi_position', points=2"):
        jc.simulate(two, two.nominal, np.zeros((2, 8)), device="position")
    with pytest.raises(ValueError, match="3 bodies .* 2 marker points"):
        jc.simulate(three, three.nominal, np.zeros((2, 8)), device=jc.make_device("multi_position", points=2))
    with pytest.raises(jc.robots.urdf.URDFError, match="not both"):
        load_urdf(urdf_path, base="base_link", tip="left_hand", tips=TIPS)
    with pytest.raises(jc.robots.urdf.URDFError, match="no <link name='nose'>"):
        load_urdf(urdf_path, base="base_link", tips=["left_hand", "nose"])


def test_jacobian_through_the_tree_matches_central_differences(tree):
    """jacfwd of the weighted residuals w.r.t. tree + device parameters vs central differences (h 1e-6):
    relative error < 1e-7."""
    dev = jc.make_device("multi_position", points=2)
    q = jnp.asarray(jc.random_configurations(tree, 5, seed=3))
    x = jnp.concatenate([jnp.asarray(jc.perturb(tree, 1e-3, seed=4)), jnp.asarray(FRAME), jnp.asarray(MARKERS)])
    y = jc.simulate(tree, tree.nominal, q, device=dev, device_params=np.concatenate([FRAME, MARKERS])).y + 1e-3
    w = residual_weights(dev, 1e-3)

    def f(v):
        return residuals(tree, dev, v, q, jnp.asarray(y), w).ravel()

    rel = rel_err(jax.jacfwd(f)(x), central_fd(f, x, h=1e-6))
    assert rel < 1e-7, rel


def _campaign(tree, n, seed, noise=5e-5):
    a_true = jc.perturb(tree, 1e-3, seed=seed)
    q = jc.random_configurations(tree, n, seed=seed + 1, margin=0.2)
    dev = jc.make_device("multi_position", points=2)
    return a_true, jc.simulate(tree, a_true, q, device=dev, noise=noise, device_params=np.concatenate([FRAME, MARKERS]),
                               seed=seed + 2)


def _write_csv(path, data, joint_names):
    """Marker k in columns xk, yk, zk, in mm; joints in degrees."""
    head = ",".join(f"{a}{k}" for k in (1, 2) for a in "xyz") + "," + ",".join(joint_names)
    rows = [",".join(f"{v:.12g}" for v in np.concatenate([data.y[i].ravel() * 1e3, np.degrees(data.q[i])]))
            for i in range(len(data.q))]
    path.write_text("# units: length=mm, angle=deg\n" + head + "\n" + "\n".join(rows) + "\n")


def test_calibrate_the_tree_from_a_csv_and_export_it(urdf_path, tree, tmp_path):
    """`jaxcal calibrate ... --tips` on two markers read in mm by a tracker 1.7 m away: the fit reaches the
    noise floor (0.05 mm per axis: 3-D RMS 0.087 mm), the held-out poses too, and the calibrated URDF
    re-read as a tree predicts what the fit predicts to 1e-12 m."""
    a_true, data = _campaign(tree, 60, seed=10)
    csv = tmp_path / "hands.csv"
    _write_csv(csv, data, tree.joint_names)
    out = tmp_path / "out"
    code = main(["calibrate", urdf_path, str(csv), "--base", "base_link", "--tips", *TIPS, "--out", str(out),
                 "--sigma-position", "5e-5", "--quiet"])
    res = json.loads((out / "results.json").read_text())
    assert code == 0, res.get("health")
    rms = res["rms"]
    assert rms["train"]["position_mm"]["before"] > 1.0
    assert 0.07 < rms["train"]["position_mm"]["after"] < 0.095
    assert rms["heldout"]["position_mm"]["after"] < 0.11
    saved = load_urdf(str(out / "twoarm_calibrated.urdf"), base="base_link", tips=TIPS)
    assert saved.n_params == tree.n_params
    a_fit = np.array([row["identified"] for row in res["parameters"][:tree.n_params]])
    assert [row["name"] for row in res["parameters"][:tree.n_params]] == list(tree.names)
    q = jc.random_configurations(tree, 5, seed=20)
    exported = jc.forward(saved, saved.nominal, q)
    fitted = jc.forward(tree, a_fit, q)
    assert np.abs(np.asarray(exported.p) - np.asarray(fitted.p)).max() < 1e-12


# ---- the gap diagnosis on a tree: whole-tree gravity at a shared joint ---------------------------------------------
def torso_pitch_load(robot, a, q) -> np.ndarray:
    """Gravity moment (kg m) about the torso pitch axis of every link it carries (torso and both arms), summed
    here from the URDF masses and the body frames (not with the diagnosis' own load code)."""
    f = jc.kin.model.frames(robot, a, q)
    R, p = np.asarray(f.R), np.asarray(f.p)
    b = robot.joint_names.index("torso_pitch")  # body 1
    axis, origin = R[:, b] @ np.array([0.0, 1.0, 0.0]), p[:, b]
    load = np.zeros(len(q))
    for k, inertia in enumerate(robot.extras["inertia"]):
        if k > b and inertia["mass"] > 0:
            com = p[:, k] + np.einsum("nij,j->ni", R[:, k], np.asarray(inertia["com"], float))
            load += inertia["mass"] * np.einsum("ni,ni->n", axis, np.cross(com - origin, [0.0, 0.0, -1.0]))
    return load


def test_gradients_of_the_gap_model_on_a_tree(tree):
    """jacfwd of the gap model's residuals (every effect, both tips) vs central differences: rel. error < 1e-6."""
    dev = jc.make_device("multi_position", points=2)
    model = gap_model(tree, dev)
    n = 4
    q = jnp.asarray(jc.random_configurations(tree, n, seed=8))
    covariates = {"time": np.linspace(0.0, 1.0, n), "temperature": np.linspace(20.0, 25.0, n),
                  "direction": np.sign(np.random.default_rng(2).standard_normal((n, tree.n_inputs)))}
    C = jnp.asarray(covariate_matrix(model, covariates, n)[0])
    x = np.asarray(model.nominal()).copy()
    x[:tree.n_params] = np.asarray(jc.perturb(tree, 1e-2, seed=9))
    x[tree.n_params:model.n_geometry] = np.concatenate([FRAME, MARKERS])
    x[model.n_geometry:] = 1e-2 * np.random.default_rng(1).standard_normal(len(model.effect_names))
    f = jax.jit(lambda v: gap_residuals(model, v, q, jnp.zeros((n, 2, 3)), C, jnp.ones(6)).reshape(-1))
    rel = rel_err(jax.jacfwd(f)(jnp.asarray(x)), central_fd(f, jnp.asarray(x), h=1e-6))
    assert rel < 1e-6, rel


@pytest.mark.slow  # 40-80 s: a 5-fold diagnosis of a 126-parameter tree
def test_diagnose_finds_torso_compliance_loaded_by_both_arms(tree):
    """A torso pitch joint that gives under the gravity moment of the torso and both arms (1.5e-4 rad per kg m,
    the readings' error 0.16 mm RMS against 0.05 mm noise per axis) is found at that joint from the two hands'
    markers, its constant within 10 %, the held-out error back to the noise floor."""
    a_true = jc.perturb(tree, 1e-3, seed=5)
    q = jc.random_configurations(tree, 120, seed=6, margin=0.2)
    q_actual = q.copy()
    q_actual[:, 1] += 1.5e-4 * torso_pitch_load(tree, a_true, q)
    dev = jc.make_device("multi_position", points=2)
    y = jc.simulate(tree, a_true, q_actual, device=dev, noise=5e-5, device_params=np.concatenate([FRAME, MARKERS]), seed=7).y
    data = jc.Dataset(q=q, y=y, device=dev, joint_names=tree.joint_names)  # the recorded joints miss the give
    d = jc.gap.diagnose(tree, data, effects=("compliance", "link_bending", "payload", "encoder_gain"), sigma_position=5e-5)
    assert d.verdict == "compliance" and d.joints == ("torso_pitch",), d.report()
    assert abs(d.parameters["gap.compliance.torso_pitch"] / 1.5e-4 - 1) < 0.1
    assert d.shrink > 0.9 and d.heldout_rms_after < 1.15 * d.noise_floor


# ---- a camera on one link reading a marker on another (head camera -> gripper) --------------------------------------
CAMERA = np.array([0.004, -0.003, 0.002, 0.01, -0.02, 0.015, 0.05, 0.01, 0.12])  # camera frame on its link, marker


def test_link_camera_reads_the_marker_in_the_moving_camera(urdf_path, tree):
    cam = jc.make_device("link_camera")
    assert cam.names[:2] == ("cam.x", "cam.y") and cam.n_params == 9 and jc.make_device("head_camera").kind == "link_camera"
    q = jc.random_configurations(tree, 3, seed=30)
    F = jc.forward(tree, tree.nominal, q)
    C = jc.measure.base.frame_from_params(jnp.asarray(CAMERA[:6]))
    for i in range(3):  # by hand: the marker in the world, into the camera link, into the camera
        world = np.asarray(F.R[i, 1]) @ CAMERA[6:] + np.asarray(F.p[i, 1])
        in_link = np.asarray(F.R[i, 0]).T @ (world - np.asarray(F.p[i, 0]))
        expected = np.asarray(C.R).T @ (in_link - np.asarray(C.p))
        got = np.asarray(cam.read(jc.Pose(F.R[i], F.p[i]), jnp.asarray(CAMERA)))
        assert np.abs(got - expected).max() < 1e-15
    with pytest.raises(ValueError, match=r"tips=\[camera link, marker link\]"):
        jc.simulate(jc.robots.get("stanford"), jc.robots.get("stanford").nominal, np.zeros((2, 6)), device=cam)


def test_link_camera_gradient_and_calibration(tree):
    """jacfwd vs central differences (< 1e-7); a calibration from 90 readings of the right hand's marker by a
    camera on the left hand (0.1 mm noise per axis) predicts 30 new ones at the noise floor, and leaves the
    torso's parameters at their prior: camera and marker both ride on the torso, so its geometry cancels out."""
    cam = jc.make_device("link_camera")
    q = jnp.asarray(jc.random_configurations(tree, 5, seed=31))
    x = jnp.concatenate([jnp.asarray(jc.perturb(tree, 1e-3, seed=32)), jnp.asarray(CAMERA)])
    y = jnp.asarray(jc.simulate(tree, tree.nominal, q, device=cam, device_params=CAMERA).y) + 1e-3
    w = residual_weights(cam, 1e-3)

    def f(v):
        return residuals(tree, cam, v, q, y, w).ravel()

    assert rel_err(jax.jacfwd(f)(x), central_fd(f, x, h=1e-6)) < 1e-7

    a_true = jc.perturb(tree, 1e-3, seed=33)
    q = jc.random_configurations(tree, 120, seed=34, margin=0.2)
    data = jc.simulate(tree, a_true, q, device=cam, noise=1e-4, device_params=CAMERA, seed=35)
    fit = jc.identify(tree, data.subset(np.arange(90)))
    floor = 1e-4 * np.sqrt(3) * 1e3  # mm, 3-D
    assert fit.rms_before > 1.0 and fit.converged
    assert fit.rms_on(data.subset(np.arange(90, 120))) < 1.2 * floor
    assert {f"torso_yaw.{p}" for p in ("x", "y", "z", "roll", "pitch", "yaw", "offset")} <= set(fit.undetermined)
