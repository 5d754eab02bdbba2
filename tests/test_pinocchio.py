"""The URDF chains' kinematics against pinocchio (an independent implementation, `pip install pin`; skipped
without it): tool rotation and position, and the tool's Jacobian with respect to the joints (linear and angular,
world-aligned at the tool), on the real robots' URDFs at random configurations."""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcal as jc
from jaxcal.kin.model import forward_open
from jaxcal.realdata import DATA_DIR, REAL_DATASETS

pin = pytest.importorskip("pinocchio")


def reduced_chain(path, joint_names, tip):
    """pinocchio's model of the URDF with every joint outside the chain locked at 0, the tip frame's id and each
    chain joint's index in its configuration vector."""
    full = pin.buildModelFromUrdf(path)
    lock = [full.getJointId(n) for n in full.names[1:] if n not in joint_names]
    model = pin.buildReducedModel(full, lock, pin.neutral(full))
    ids = [model.getJointId(n) for n in joint_names]
    assert all(model.joints[i].nq == 1 for i in ids)
    return model, model.getFrameId(tip), np.array([model.joints[i].idx_q for i in ids])


@pytest.mark.parametrize("dataset", ["talos", "ur10", "tiago"])
def test_tool_pose_and_joint_jacobian_match_pinocchio(dataset):
    spec = REAL_DATASETS[dataset]
    rb = jc.robots.get(spec["robot"])
    model, fid, idx = reduced_chain(os.path.join(DATA_DIR, spec["folder"], spec["urdf"]), rb.joint_names, spec["tip"])
    data = model.createData()
    a = jnp.asarray(rb.nominal_np)
    q = jc.random_configurations(rb, 16, seed=5)
    R, p = (np.asarray(v) for v in forward_open(rb, a, jnp.asarray(q)))
    dR, dp = (np.asarray(v) for v in jax.vmap(jax.jacfwd(lambda qi: forward_open(rb, a, qi)))(jnp.asarray(q)))
    for i in range(len(q)):
        qp = np.zeros(model.nq)
        qp[idx] = q[i]
        pin.framesForwardKinematics(model, data, qp)
        np.testing.assert_allclose(R[i], data.oMf[fid].rotation, atol=1e-12)
        np.testing.assert_allclose(p[i], data.oMf[fid].translation, atol=1e-12)
        J = pin.computeFrameJacobian(model, data, qp, fid, pin.LOCAL_WORLD_ALIGNED)[:, idx]
        np.testing.assert_allclose(dp[i], J[:3], atol=1e-12)
        # dR/dq_j R^T = [omega_j]x: the angular columns
        W = np.einsum("abj,cb->jac", dR[i], R[i])
        omega = np.stack([W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]])
        np.testing.assert_allclose(omega, J[3:], atol=1e-12)
