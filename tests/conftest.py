import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import jax  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

import jaxcal  # noqa: E402,F401  (float64 + compilation cache)

jax.config.update("jax_enable_x64", True)


def central_fd(f, x, h=1e-6):
    """Central finite-difference Jacobian of f: R^n -> R^m (numpy, float64)."""
    x = np.asarray(x, float)
    f0 = np.asarray(f(x)).reshape(-1)
    J = np.zeros((f0.size, x.size))
    for i in range(x.size):
        e = np.zeros_like(x)
        e[i] = h
        J[:, i] = (np.asarray(f(x + e)).reshape(-1) - np.asarray(f(x - e)).reshape(-1)) / (2 * h)
    return J


def rel_err(A, B):
    A, B = np.asarray(A), np.asarray(B)
    return np.linalg.norm(A - B) / max(np.linalg.norm(B), 1e-300)


@pytest.fixture
def rng():
    return np.random.default_rng(1234)
