"""Scale-out on two host CPU devices (a subprocess with XLA_FLAGS forcing two devices): a batch of
while-loop solves (fast, ~10 s of CPU), the fleet identification and the Monte Carlo (slow: 35 s and
80 s of CPU, mostly compiling the vmapped LM per slice shape) give the same numbers sharded and unsharded."""

import json
import os
import subprocess
import sys
import textwrap

import pytest

FLEET = textwrap.dedent("""
    import json
    import jax
    import numpy as np
    import jaxcal as jc
    from jaxcal.scale import identify_fleet

    devs = jax.devices()
    assert len(devs) == 2, devs
    rb = jc.robots.get("mrr1")
    q = jc.random_configurations(rb, 30, seed=1)
    fleet = [jc.simulate(rb, jc.perturb(rb, 0.002, seed=10 + k), jc.random_configurations(rb, 30, seed=20 + k),
                         noise=1e-5, seed=30 + k) for k in range(N_ROBOTS)]
    one = identify_fleet(rb, fleet, devices=devs[:1], sigma_position=1e-5)
    two = identify_fleet(rb, fleet, devices=devs, sigma_position=1e-5)
    out = {"fleet_max_diff": float(np.abs(one.a_full - two.a_full).max()), "fleet_rms": two.rms_after.tolist(),
           "fleet_converged": bool(two.converged.all()), "fleet_devices": two.timings["devices"]}
    if FULL:
        out["serial_rms"] = [jc.identify(rb, d, sigma_position=1e-5).rms_after for d in fleet]
        mc1 = jc.uncertainty.monte_carlo(rb, jc.perturb(rb, 0.002, seed=3), q, noise={"position": 1e-5}, runs=8, chunk=8,
                                         devices=devs[:1], sigma_position=1e-5)
        mc2 = jc.uncertainty.monte_carlo(rb, jc.perturb(rb, 0.002, seed=3), q, noise={"position": 1e-5}, runs=8, chunk=8,
                                         devices=devs, sigma_position=1e-5)
        out.update(mc_max_diff=float(np.abs(mc1.estimates - mc2.estimates).max()), mc_devices=mc2.timings["devices"])
    print(json.dumps(out))
""")


IK = textwrap.dedent("""
    import json
    import jax
    import jax.numpy as jnp
    import numpy as np
    import jaxcal as jc
    from jaxcal.scale import over_devices

    devs = jax.devices()
    assert len(devs) == 2, devs
    rb = jc.robots.get("mrr1")

    def ik(q0, target, a):
        # Gauss-Newton position IK in a while loop (the pattern that deadlocked under a NamedSharding)
        p = lambda q: jc.forward(rb, a, q).p
        def body(s):
            q, k, _ = s
            r = target - p(q)
            return q + jnp.linalg.solve(jax.jacfwd(p)(q), r), k + 1, jnp.linalg.norm(r)
        q, k, res = jax.lax.while_loop(lambda s: (s[2] > 1e-13) & (s[1] < 50), body, (q0, 0, jnp.inf))
        return q, k

    fn = jax.jit(lambda b, a: jax.vmap(ik, (0, 0, None))(b["q0"], b["target"], a))
    q_true = jc.random_configurations(rb, 64, seed=1, margin=0.2)
    target = np.asarray(jc.forward(rb, rb.nominal, q_true).p)
    batch = {"q0": q_true + 0.05, "target": target}
    q1, k1 = over_devices(fn, batch, rb.nominal, devs[:1])
    q2, k2 = over_devices(fn, batch, rb.nominal, devs)
    err = np.abs(np.asarray(jc.forward(rb, rb.nominal, q2).p) - target).max()
    print(json.dumps({"max_diff": float(np.abs(q1 - q2).max()), "ik_error": float(err), "iterations": int(k2.max())}))
""")


def _run(script: str):
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2", OPENBLAS_NUM_THREADS="1",
               JAX_PLATFORMS="cpu")
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env["PYTHONPATH"] = root + os.pathsep + env.get("PYTHONPATH", "")
    proc = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=900, cwd=root)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_sharded_batch_of_while_loops_equals_unsharded():
    r = _run(IK)
    assert r["max_diff"] < 1e-12  # the same program on each device's half of the batch
    assert r["ik_error"] < 1e-10 and r["iterations"] < 50


def _run_on_two_devices(full: bool):
    return _run(f"FULL = {full}\nN_ROBOTS = {5 if full else 2}\n" + FLEET)


@pytest.mark.slow
def test_sharded_fleet_identification_equals_unsharded():
    r = _run_on_two_devices(full=False)
    assert r["fleet_devices"] == 2 and r["fleet_converged"]
    assert r["fleet_max_diff"] < 1e-12  # the same compiled solve per robot, only placed on another device
    assert max(r["fleet_rms"]) < 0.05  # 0.01 mm noise, 2 mm errors


@pytest.mark.slow
def test_sharded_fleet_and_monte_carlo_full():
    r = _run_on_two_devices(full=True)
    assert r["fleet_max_diff"] < 1e-12 and r["fleet_converged"]
    # each robot's fleet fit is as good as its own serial identification
    for fleet, serial in zip(r["fleet_rms"], r["serial_rms"]):
        assert abs(fleet - serial) < 1e-6 * serial + 1e-9, (fleet, serial)
    assert r["mc_devices"] == 2 and r["mc_max_diff"] < 1e-12
