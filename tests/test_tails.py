"""jaxcal.tails (chi-square, F and normal tails from scipy.special) against scipy.stats."""

import numpy as np
import pytest
import scipy.stats

from jaxcal import tails


@pytest.mark.parametrize("k", [1, 2, 3, 7.5, 40, 300])
def test_chi2_quantile_and_tail_match_scipy_stats(k):
    q = np.linspace(0.0, 1.0, 101)
    np.testing.assert_allclose(tails.chi2_ppf(q, k), scipy.stats.chi2.ppf(q, k), rtol=1e-12, atol=0)
    assert tails.chi2_ppf(1.0, k) == np.inf and tails.chi2_ppf(0.0, k) == 0.0
    x = np.linspace(0.0, 3.0 * k + 50.0, 401)
    np.testing.assert_allclose(tails.chi2_sf(x, k), scipy.stats.chi2.sf(x, k), rtol=1e-12, atol=1e-300)
    np.testing.assert_allclose(tails.chi2_sf(tails.chi2_ppf(0.95, k), k), 0.05, rtol=1e-10)


@pytest.mark.parametrize("k1,k2", [(1, 1), (3, 10), (18, 400)])
def test_f_tail_matches_scipy_stats(k1, k2):
    x = np.linspace(0.0, 25.0, 401)
    np.testing.assert_allclose(tails.f_sf(x, k1, k2), scipy.stats.f.sf(x, k1, k2), rtol=1e-12, atol=1e-300)


def test_normal_tail_matches_scipy_stats():
    z = np.linspace(-30.0, 30.0, 601)
    np.testing.assert_allclose(tails.norm_sf(z), scipy.stats.norm.sf(z), rtol=1e-12, atol=1e-300)
    assert tails.norm_sf(0.0) == 0.5


def test_the_cli_does_not_import_scipy_stats():
    """`import scipy.stats` costs ~0.5 s of every `jaxcal` command; the analyses use jaxcal.tails instead."""
    import subprocess
    import sys

    code = "import sys, jaxcal, jaxcal.cli, jaxcal.gap; print('scipy.stats' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
