"""Latin hypercube sampling (Ren et al. 2013, Appendix A)."""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from jprt.render.sampling import latin_hypercube


@settings(max_examples=30, deadline=None)
@given(n=st.integers(1, 50), d=st.integers(1, 5), seed=st.integers(0, 1000))
def test_one_sample_per_stratum(n, d, seed):
    rng = np.random.default_rng(seed)
    lo = rng.uniform(-2, 0, d)
    hi = lo + rng.uniform(0.1, 3, d)
    x = latin_hypercube(np.random.default_rng(seed), n, lo, hi)
    assert x.shape == (n, d)
    assert np.all((x >= lo) & (x <= hi))
    strata = np.floor((x - lo) / (hi - lo) * n).astype(int)
    for a in range(d):
        assert sorted(strata[:, a]) == list(range(n))


def test_degenerate_and_bad_boxes():
    x = latin_hypercube(np.random.default_rng(0), 4, [0, 1], [1, 1])
    assert np.all(x[:, 1] == 1)
    with pytest.raises(ValueError, match="lo <= hi"):
        latin_hypercube(np.random.default_rng(0), 4, [0, 1], [1, 0])
    with pytest.raises(ValueError, match="at least one"):
        latin_hypercube(np.random.default_rng(0), 0, [0], [1])
