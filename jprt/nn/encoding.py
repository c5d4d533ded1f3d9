"""Input encodings for network inputs (no learned state).

* ``sh4``: real spherical harmonics of a direction, 4 bands = 16 features (tiny-cuda-nn's
  "SphericalHarmonics" degree 4; Raghavan et al. 2023 §5 encode the reflected direction so).
* ``one_blob``: Müller et al. 2019's one-blob encoding: a Gaussian kernel (sigma = 1 / bins) of a
  scalar in [0, 1] evaluated at the bin centres.
* ``roughness_remap``: log(25 sigma + 1) / log(26) (Raghavan et al. 2023 §5), more resolution at
  low roughness.
"""

from __future__ import annotations

import math

import jax.numpy as jnp

from jprt.sphere import sh

__all__ = ["sh4", "sh_encoding", "one_blob", "roughness_remap"]


def sh_encoding(d, bands: int = 4):
    """SH encoding of unit directions (..., 3) -> (..., bands^2) (see ``jprt.sphere.sh.encode``).

    Numerics:
        d: (32, 3) unit
        bands: = 4
        float32: value rtol 1e-5 atol 1e-6; grad rtol 1e-4 atol 1e-5
    """
    return sh.encode(d, bands)


def sh4(d):
    """The 16-feature SH encoding of Raghavan et al. 2023 (bands 0..3).

    Numerics:
        d: (32, 3) unit
        float32: value rtol 1e-5 atol 1e-6; grad rtol 1e-4 atol 1e-5
    """
    return sh.encode(d, 4)


def one_blob(x, bins: int = 16):
    """One-blob encoding of scalars x (...) in [0, 1] -> (..., bins).

    Numerics:
        x: (32,) in [0, 1]
        bins: = 16
        float32: value rtol 1e-5 atol 1e-7; grad rtol 1e-4 atol 1e-6
    """
    x = jnp.asarray(x)
    centres = (jnp.arange(bins, dtype=x.dtype) + 0.5) / bins
    sigma = 1.0 / bins
    diff = x[..., None] - jnp.broadcast_to(centres, x.shape + (bins,))
    return jnp.exp(-0.5 * jnp.square(diff / sigma))


def roughness_remap(sigma):
    """log(25 sigma + 1) / log(26): maps [0, 1] to [0, 1], stretched near 0.

    Numerics:
        sigma: (32,) in [0, 1]
        float32: value rtol 1e-6 atol 0; grad rtol 1e-6 atol 0
    """
    return jnp.log1p(25.0 * jnp.asarray(sigma)) / math.log(26.0)
