"""Sample-count buckets (`jaxcal.fit.buckets`): one compiled program serves datasets of nearby sizes, and its fit is
the fit of the caller's samples alone."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcal as jc
from jaxcal.fit import buckets, core
from jaxcal.fit.buckets import padded_solver_args, sample_bucket


@pytest.mark.parametrize("per_octave", [1, 2, 4, 8, 16])
def test_a_bucket_rounds_up_by_less_than_one_part_in_per_octave(per_octave):
    """sample_bucket(n) >= n, grows with n, pads by less than n / per_octave, and there are per_octave buckets in
    each octave (2^k, 2^(k+1)] once 2^k >= per_octave; 0 buckets per octave leave n as it is."""
    n = np.arange(1, 5000)
    b = np.array([sample_bucket(int(k), per_octave) for k in n])
    assert np.all(b >= n) and np.all(np.diff(b) >= 0)
    assert np.all((b - n) * per_octave < n), np.max((b - n) / n)
    for k in range(int(np.log2(per_octave)), 12):
        assert len({sample_bucket(m, per_octave) for m in range(2**k + 1, 2 ** (k + 1) + 1)}) == per_octave
    assert [sample_bucket(m, 0) for m in (1, 17, 200, 1001)] == [1, 17, 200, 1001]
    assert sample_bucket(200, 8) == 208 and sample_bucket(125, 8) == 128 and sample_bucket(61, 8) == 64


def test_padding_repeats_a_sample_in_use_with_weight_zero(monkeypatch):
    """The padded arguments: q, y and cov repeat the first sample of non-zero weight (here the second: the first has
    weight 0 in every batch entry), w and a given start's data rows are 0 past the caller's samples, a placeholder
    start is made at the padded shape, batched entries are padded along their sample axis (1), and a JAX array is
    padded as one (with the same values)."""
    monkeypatch.setattr(buckets, "SAMPLE_BUCKETS_PER_OCTAVE", 2)
    n, m, P = 19, 3, 4  # bucket 24
    rng = np.random.default_rng(0)
    q, y, cov = rng.normal(size=(n, 2)), rng.normal(size=(n, m)), rng.normal(size=(n, 1))
    w = np.ones((n, m))
    w[0] = 0.0
    start = dict(r=rng.normal(size=n * m), J=rng.normal(size=(n * m, P)), given=np.float64(1.0))
    out = padded_solver_args(dict(q=q, y=y, cov=cov, w=w, mask=np.ones(P), start=start))
    assert out["q"].shape == (24, 2) and out["y"].shape == (24, m) and out["cov"].shape == (24, 1)
    np.testing.assert_array_equal(out["q"][:n], q)
    np.testing.assert_array_equal(out["q"][n:], np.repeat(q[1:2], 5, axis=0))
    np.testing.assert_array_equal(out["y"][n:], np.repeat(y[1:2], 5, axis=0))
    assert not out["w"][n:].any() and np.array_equal(out["w"][:n], w)
    assert out["start"]["r"].shape == (24 * m,) and not out["start"]["r"][n * m:].any()
    assert out["start"]["J"].shape == (24 * m, P) and not out["start"]["J"][n * m:].any()
    np.testing.assert_array_equal(out["mask"], np.ones(P))
    made = []
    blank = dict(start, r=np.zeros(n * m), J=np.zeros((n * m, P)), given=np.float64(0.0))
    out = padded_solver_args(dict(q=q, y=y, cov=cov, w=w, start=blank), placeholder=lambda s: made.append(s) or np.zeros(s))
    assert made == [(24 * m,), (24 * m, P)]
    wb = np.stack([w, w])
    out = padded_solver_args(dict(q=q, y=np.stack([y, y]), cov=cov, w=wb), batched=("y", "w"))
    assert out["y"].shape == (2, 24, m) and out["w"].shape == (2, 24, m) and out["q"].shape == (24, 2)
    np.testing.assert_array_equal(out["y"][:, n:], np.repeat(y[None, 1:2], 5, axis=1).repeat(2, axis=0))
    on_device = padded_solver_args(dict(q=q, y=jnp.stack([y, y]), cov=cov, w=wb), batched=("y", "w"))  # stays a JAX array
    assert isinstance(on_device["y"], jax.Array) and np.array_equal(np.asarray(on_device["y"]), out["y"])


def _solver_compiles(monkeypatch) -> list:
    calls = []
    spied = core.compile_solver
    monkeypatch.setattr(core, "compile_solver", lambda *a, **k: calls.append(1) or spied(*a, **k))
    return calls


# the four-bar (a closed mechanism: the repeated samples close as theirs do) compiles its solver twice, ~30 s of CI: a
# slow study; the fast suite's closed-loop identify on padded rows is the delta-theodolite tutorial (125 -> 128 samples)
@pytest.mark.parametrize("name", ["stanford", pytest.param("fourbar2d", marks=pytest.mark.slow)])
def test_a_bucket_program_fits_the_samples_alone_and_serves_nearby_counts(name, monkeypatch):
    """identify on 45 samples (program for 48 at 8 buckets per octave) equals identify in a program for exactly 45
    (same steps, estimate to 1e-10, RMS to 1e-9 relative); the device frame is 2 m away and turned. Then 46 and 47
    samples compile no solver: they run in the program for 48."""
    monkeypatch.setattr(buckets, "SAMPLE_BUCKETS_PER_OCTAVE", 8)
    rb = jc.robots.get(name)
    dev = jc.make_device("position")
    d = np.zeros(dev.n_params)
    d[:6] = [1.5, -1.1, 0.7, 0.4, -0.9, 1.2]
    every = jc.simulate(rb, jc.perturb(rb, 1e-3, seed=1), jc.random_configurations(rb, 47, seed=2), dev, noise=1e-5,
                        device_params=d, seed=3)
    data = every.subset(np.arange(45))
    assert sample_bucket(45) == sample_bucket(46) == sample_bucket(47) == 48
    fit = jc.identify(rb, data, sigma_position=1e-5)
    with monkeypatch.context() as exact_sizes:
        exact_sizes.setattr(buckets, "SAMPLE_BUCKETS_PER_OCTAVE", 0)
        exact = jc.identify(rb, data, sigma_position=1e-5)
    assert fit.iterations == exact.iterations and fit.estimated == exact.estimated
    np.testing.assert_allclose(np.asarray(fit.a_full), np.asarray(exact.a_full), rtol=0, atol=1e-10)
    assert abs(fit.rms_after - exact.rms_after) <= 1e-9 * exact.rms_after
    compiles = _solver_compiles(monkeypatch)
    for n in (46, 47):
        part = jc.identify(rb, every.subset(np.arange(n)), sigma_position=1e-5)
        assert part.converged and part.timings["compile_s"] == 0.0
    assert compiles == []
