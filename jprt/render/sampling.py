"""Sampling designs for training data: Latin hypercube samples in boxes.

Ren et al. 2013, Appendix A: "we uniformly subdivide the light range into N_l strata and randomly
sample the light position in each stratum" (Latin hypercube sampling, McKay et al.): along every
dimension the n samples fall one per stratum [k/n, (k+1)/n), with the strata of different
dimensions paired by independent random permutations.
"""

from __future__ import annotations

import numpy as np

__all__ = ["latin_hypercube", "check_box"]


def check_box(lo, hi, name: str = "box") -> tuple[np.ndarray, np.ndarray]:
    """``(lo, hi)`` as float64 arrays of equal shape with lo <= hi, or a one-line ValueError."""
    lo = np.asarray(lo, np.float64).reshape(-1)
    hi = np.asarray(hi, np.float64).reshape(-1)
    if lo.shape != hi.shape or lo.size == 0:
        raise ValueError(f"{name}: corners {lo.tolist()} and {hi.tolist()} need the same non-zero length")
    if not (np.isfinite(lo).all() and np.isfinite(hi).all()) or np.any(hi < lo):
        raise ValueError(f"{name}: need finite corners with lo <= hi, got lo={lo.tolist()} hi={hi.tolist()}")
    return lo, hi


def latin_hypercube(rng: np.random.Generator, n: int, lo, hi) -> np.ndarray:
    """``n`` Latin-hypercube samples (n, D) in the box [lo, hi] (D = len(lo)).

    Each coordinate has exactly one sample in each of its n equal strata; degenerate dimensions
    (lo == hi) are constant.
    """
    lo, hi = check_box(lo, hi)
    n = int(n)
    if n <= 0:
        raise ValueError(f"need at least one sample, got n={n}")
    d = lo.size
    strata = np.stack([rng.permutation(n) for _ in range(d)], axis=1)
    u = (strata + rng.random((n, d))) / n
    return lo + (hi - lo) * u
