"""Base set (seed 001 eq 33-37) when the observation matrix has fewer rows than columns."""

import numpy as np

from jaxcal.fit.base import base_set


def test_fewer_rows_than_columns_keeps_rank_many_and_regroups_the_rest():
    rng = np.random.default_rng(0)
    W = rng.standard_normal((3, 5))
    W[:, 4] = 0.0  # a column with no effect
    bs = base_set(W, priority=np.ones(5))
    assert bs.independent.size == 3  # rank of a generic 3 x 4 block
    assert set(bs.independent) | set(bs.regrouped) | set(bs.no_effect) == set(range(5))
    assert list(bs.no_effect) == [4] and bs.regrouped.size == 1
    np.testing.assert_allclose(W[:, bs.independent] @ bs.beta, W[:, bs.regrouped], atol=1e-12)
