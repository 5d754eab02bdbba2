"""Forward kinematics and the tool's position Jacobian (with respect to the joints) against pinocchio, on one
URDF, in one process: the TALOS left arm (base_link -> gripper_left_base_link, 9 revolute joints, the real URDF
packaged with jaxcal's real datasets).

jaxcal: `jax.jit(jax.vmap(...))` over N configurations (one call; the Jacobian by `jax.jacrev`). pinocchio
(optional, `pip install pin`): its C++ `framesForwardKinematics` / `computeFrameJacobian` called once per
configuration from a Python loop (it has no batched call), on the model reduced to the chain's joints
(`buildReducedModel`, the others locked at 0). Both must agree (positions to 1e-12 m, Jacobians to 1e-12)
before a time is reported. Compile time apart, medians. Run: python benchmarks/pinocchio_fk.py [--n 10000]
"""

from __future__ import annotations

import argparse
import os
import time

import jax
import jax.numpy as jnp
import numpy as np
from _common import median_time

import jaxcal as jc
from jaxcal.kin.model import forward_open
from jaxcal.realdata import DATA_DIR, REAL_DATASETS
from jaxcal.robots.urdf import load_urdf

TALOS = os.path.join(DATA_DIR, REAL_DATASETS["talos"]["folder"], REAL_DATASETS["talos"]["urdf"])
BASE, TIP = "base_link", REAL_DATASETS["talos"]["tip"]


def pinocchio_chain(path: str, joint_names):
    """(model, data, frame id of TIP, q index of each joint in `joint_names`) of the URDF reduced to those joints."""
    import pinocchio as pin

    full = pin.buildModelFromUrdf(path)
    lock = [full.getJointId(n) for n in full.names[1:] if n not in joint_names]
    model = pin.buildReducedModel(full, lock, pin.neutral(full))
    idx = np.array([model.joints[model.getJointId(n)].idx_q for n in joint_names])
    return model, model.createData(), model.getFrameId(TIP), idx


def main(n: int = 10_000) -> list[dict]:
    """One dict per quantity (FK, position Jacobian): compile s, jaxcal s, pinocchio s (NaN without pinocchio)."""
    path = TALOS
    rb = load_urdf(path, base=BASE, tip=TIP)
    a = jnp.asarray(rb.nominal_np)
    q = jc.random_configurations(rb, n, seed=1)
    qj = jnp.asarray(q)
    position = lambda a, qi: forward_open(rb, a, qi)[1]  # noqa: E731
    programs = {"FK": jax.jit(jax.vmap(position, (None, 0))),
                # reverse mode: 3 outputs, 9 inputs (jax.jacfwd took 134 ms against 39 ms at N = 1e4)
                "position Jacobian w.r.t. the joints": jax.jit(jax.vmap(jax.jacrev(position, 1), (None, 0)))}
    try:
        import pinocchio as pin

        model, data, fid, idx = pinocchio_chain(path, rb.joint_names)
    except ImportError:
        pin = None
    rows = []
    for what, program in programs.items():
        t = time.perf_counter()
        out = np.asarray(program(a, qj))
        compile_s = time.perf_counter() - t
        t_jc = median_time(lambda: program(a, qj).block_until_ready(), repeat=5)
        t_pin = float("nan")
        if pin is not None:
            qp = np.zeros((n, model.nq))
            qp[:, idx] = q
            if what == "FK":
                def run():
                    out = np.empty((n, 3))
                    for i in range(n):
                        pin.framesForwardKinematics(model, data, qp[i])
                        out[i] = data.oMf[fid].translation
                    return out
            else:
                def run():
                    out = np.empty((n, 3, len(idx)))
                    for i in range(n):
                        out[i] = pin.computeFrameJacobian(model, data, qp[i], fid, pin.LOCAL_WORLD_ALIGNED)[:3, idx]
                    return out
            ref = run()
            err = float(np.max(np.abs(out - ref)))
            if err > 1e-12:
                raise AssertionError(f"{what}: jaxcal and pinocchio differ by {err:.2e} on the same URDF")
            t_pin = median_time(run, repeat=3)
        rows.append({"what": what, "n": n, "compile_s": compile_s, "t_jc": t_jc, "t_pin": t_pin})
        print(f"{what}, TALOS left arm, N = {n}: compile {compile_s:.2f} s, jaxcal {t_jc * 1e3:.2f} ms, pinocchio "
              f"{t_pin * 1e3:.1f} ms ({t_pin / n * 1e6:.2f} us a configuration), {t_pin / t_jc:.1f}x")
    return rows


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=10_000)
    main(ap.parse_args().n)
