"""Forward kinematics in the three conventions, robot files, and gradient checks (jacfwd vs
central finite differences, float64)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import central_fd, rel_err
from helpers import mcpc_spatial

import jaxcal as jc
from jaxcal.robots import RobotFileError, mcpc_robot, pry_robot


def test_mrr1_table_6_6_nominal_tip():
    rb = jc.robots.get("mrr1")
    assert len(rb.names) == 18 and rb.n_inputs == 3
    pose = jc.forward(rb, rb.nominal, rb.home)
    np.testing.assert_allclose(pose.p, [0.4330127, 0.65, 0.25], atol=1e-7)
    np.testing.assert_allclose(pose.R, [[0, -1, 0], [-1, 0, 0], [0, 0, -1]], atol=1e-12)


def test_stanford_parameter_table():
    rb = jc.robots.get("stanford")
    assert len(rb.names) == 43 and rb.n_inputs == 6
    assert rb.names[:2] == ("j0.theta", "j0.r") and rb.names[-6:] == tuple(f"j{j}.K" for j in range(1, 7))


def test_stanford_matches_independent_dh_product():
    """Compose seed 001 eq 3 by hand with 4x4 matrices (numpy) and compare."""
    rb = jc.robots.get("stanford")
    q = np.array([0.3, -0.4, 0.55, 1.0, 0.8, -0.6])
    a = np.asarray(jc.perturb(rb, 0.01, seed=3))

    def Rx(t):
        c, s = np.cos(t), np.sin(t)
        return np.array([[1, 0, 0, 0], [0, c, -s, 0], [0, s, c, 0], [0, 0, 0, 1]])

    def Ry(t):
        c, s = np.cos(t), np.sin(t)
        return np.array([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1]])

    def Rz(t):
        c, s = np.cos(t), np.sin(t)
        return np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])

    def Tr(x, y, z):
        T = np.eye(4)
        T[:3, 3] = x, y, z
        return T

    v = dict(zip(rb.names, a))
    T = Rz(v["j0.theta"]) @ Tr(0, 0, v["j0.r"])
    for j in range(1, 8):
        th, r = v[f"j{j}.theta"], v[f"j{j}.r"]
        if j <= 6:
            qj = v[f"j{j}.K"] * q[j - 1]
            th, r = (th, r + qj) if j == 3 else (th + qj, r)
        T = T @ Ry(v[f"j{j}.beta"]) @ Rx(v[f"j{j}.alpha"]) @ Tr(v[f"j{j}.d"], 0, 0) @ Rz(th) @ Tr(0, 0, r)
    pose = jc.forward(rb, jnp.asarray(a), q)
    np.testing.assert_allclose(pose.matrix(), T, atol=1e-13)


def test_pry_module_kinds_and_mcpc_chain():
    rb = pry_robot("allkinds", (0, 0, 0.1), [
        ("cylindrical", (0.1, 0, 0), (0, 0, 0)),
        ("universal", (0.2, 0, 0), (0.1, 0, 0)),
        ("spherical", (0, 0, 0.1), (0, 0.2, 0)),
    ])
    assert rb.n_inputs == 7
    q = jnp.array([0.3, 0.05, 0.2, -0.1, 0.4, 0.5, 0.6])
    p = jc.forward(rb, rb.nominal, q)
    assert np.isfinite(np.asarray(p.p)).all()
    # MCPC: rotary chain in the plane equals the planar two-link formula
    mc = mcpc_robot("planar", [
        [0, 0, 0, 0, 0, 0, 0, 0, 0],
        [0, 0, 0, 0.7, 0, 0, 1, 0, 0],
        [0, 0, 0, 0.5, 0, 0, 2, 0, 3],
    ])
    t1, t2 = 0.4, -0.9
    pose = jc.forward(mc, mc.nominal, jnp.array([t1, t2]))
    np.testing.assert_allclose(pose.p[:2], [0.7 * np.cos(t1) + 0.5 * np.cos(t1 + t2),
                                            0.7 * np.sin(t1) + 0.5 * np.sin(t1 + t2)], atol=1e-14)


def test_batched_forward_shapes():
    rb = jc.robots.get("stanford")
    q = jc.random_configurations(rb, 12).reshape(3, 4, 6)
    pose = jc.forward(rb, rb.nominal, q)
    assert pose.R.shape == (3, 4, 3, 3) and pose.p.shape == (3, 4, 3)
    one = jc.forward(rb, rb.nominal, q[1, 2])
    np.testing.assert_allclose(pose.p[1, 2], one.p, atol=1e-15)


@pytest.mark.parametrize("name", ["mrr1", "stanford", "mcpc"])
def test_forward_gradient_matches_central_fd(name):
    """jacfwd of the tool pose w.r.t. all parameters vs central FD; relative error < 1e-7."""
    rb = mcpc_spatial() if name == "mcpc" else jc.robots.get(name)
    a0 = np.asarray(jc.perturb(rb, 0.01, seed=5))
    q = jc.random_configurations(rb, 3, seed=1)

    def f(a):
        pose = jc.forward(rb, jnp.asarray(a), q)
        return jnp.concatenate([pose.p.reshape(-1), pose.R.reshape(-1)])

    J = np.asarray(jax.jacfwd(f)(jnp.asarray(a0)))
    err = rel_err(J, central_fd(f, a0))
    assert err < 1e-7, f"{name}: relative error {err:.2e}"


@pytest.mark.parametrize("kind", ["position", "pose", "orientation", "three_point"])
def test_device_gradient_matches_central_fd(kind):
    """jacfwd of the readings w.r.t. robot + device parameters vs central FD."""
    rb = jc.robots.get("stanford")
    dev = jc.make_device(kind)
    q = jc.random_configurations(rb, 3, seed=2)
    x0 = np.concatenate([np.asarray(jc.perturb(rb, 0.01, seed=5)), 0.05 * np.random.default_rng(0).normal(size=dev.n_params)])

    @jax.jit  # compiled whole: op by op, its operations compiled ~45 small programs (~0.5 s a device kind)
    def f(x):
        x = jnp.asarray(x)
        tips = jc.forward(rb, x[:rb.n_params], q)
        return jax.vmap(dev.read, (0, None))(tips, x[rb.n_params:]).reshape(-1)

    J = np.asarray(jax.jacfwd(f)(jnp.asarray(x0)))
    err = rel_err(J, central_fd(f, x0))
    assert err < 1e-7, f"{kind}: relative error {err:.2e}"


def test_three_point_orientation_recovers_rotation(rng):
    from jaxcal.kin.rotations import exp_so3
    from jaxcal.measure import three_point_orientation

    P0 = rng.normal(size=(3, 3))
    R = exp_so3(jnp.asarray(rng.normal(size=3)))
    P1 = (R @ P0.T).T + np.array([0.1, 0.2, 0.3])
    np.testing.assert_allclose(three_point_orientation(jnp.asarray(P0), jnp.asarray(P1)), R, atol=1e-12)


def test_robot_yaml_round_trip_and_seed_layout(tmp_path):
    for name in ("mrr1", "stanford"):
        rb = jc.robots.get(name)
        a = jc.perturb(rb, 0.01, seed=1)
        path = tmp_path / f"{name}.yaml"
        jc.save_robot(rb, str(path), a=a)
        back = jc.load_robot(str(path))
        assert back.names == rb.names
        q = jc.random_configurations(rb, 5)
        np.testing.assert_allclose(jc.forward(back, back.nominal, q).matrix(), jc.forward(rb, a, q).matrix(), atol=1e-14)
    mc = mcpc_spatial()
    jc.save_robot(mc, str(tmp_path / "mc.yaml"))
    back = jc.load_robot(str(tmp_path / "mc.yaml"))
    q = jc.random_configurations(mc, 4)
    np.testing.assert_allclose(jc.forward(back, back.nominal, q).p, jc.forward(mc, mc.nominal, q).p, atol=1e-14)


@pytest.mark.parametrize("text, needle", [
    ("convention: pry\njoints:\n  - [0.5, 0, x, 0, 0, 0, R]\n", "row 1, field 'z'"),
    ("convention: pry\njoints:\n  - [0.5, 0, 0, 0, 0, 0, Q]\n", "row 1, field 'type'"),
    ("convention: pry\njoints:\n  - [0.5, 0, 0, 0, 0, R]\n", "row 1: expected 7 fields"),
    ("convention: dh\n", "field 'convention'"),
    ("convention: mdh\nframes:\n  - [2, 0, 0, 0, 0.5, 0, 0]\n  - [5, 0, 0, 0, 0, 0, 1]\n", "frame 1: sigma"),
    ("convention: mcpc\nrows:\n  - [0, 0, 0, 0, 0, 0, 3, 0, 0]\n", "field 'predecessor'"),
    ("convention: mcpc\nrows:\n  - [0, 0, 0, 0, 0, 0.1, 0, 0, 0]\n", "field 'd3' is unused"),
    ("convention: pry\nunits: {angle: grad}\njoints: [[0,0,0,0,0,0,R]]\n", "units.angle"),
    ("a: [1, 2\n", "not valid YAML"),
])
def test_bad_robot_files_name_the_place(tmp_path, text, needle):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(RobotFileError) as err:
        jc.load_robot(str(path))
    assert needle in str(err.value) and "bad.yaml" in str(err.value)
