"""Independent NumPy/SciPy references for tests and benchmarks: float64 polar-grid quadrature
dense around a pole (closed forms of sharp lobes: SG integrals, products, convolutions) and real
spherical harmonics built from ``scipy.special.sph_harm_y``."""

import numpy as np


def frame(axis):
    """An orthonormal pair (x, y) perpendicular to unit ``axis`` (NumPy, float64).

    Numerics: not differentiable (a float64 NumPy reference for tests).
    """
    axis = np.asarray(axis, np.float64)
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, axis)
    x /= np.linalg.norm(x)
    return x, np.cross(axis, x)


def polar_grid(pole, n_theta=1500, n_phi=400):
    """Directions and solid-angle weights of a polar grid around ``pole`` with theta = pi t^2,
    dense near the pole (where sharp lobes centred there live).

    Numerics: not differentiable (a float64 NumPy reference for tests).
    """
    t = (np.arange(n_theta) + 0.5) / n_theta
    theta = np.pi * t * t
    dtheta = 2.0 * np.pi * t / n_theta
    phi = 2.0 * np.pi * (np.arange(n_phi) + 0.5) / n_phi
    x, y = frame(pole)
    st, ct = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
    d = st * (np.cos(phi)[None, :, None] * x + np.sin(phi)[None, :, None] * y) + ct * np.asarray(pole, np.float64)
    w = (np.sin(theta) * dtheta)[:, None] * (2.0 * np.pi / n_phi) * np.ones((1, n_phi))
    return d.reshape(-1, 3), w.reshape(-1)


def integrate(f, pole, **grid):
    """int_S2 f by the polar grid around ``pole`` (``polar_grid``'s keywords), in float64.

    Numerics: not differentiable (a float64 NumPy reference for tests).
    """
    d, w = polar_grid(pole, **grid)
    return float(np.sum(np.asarray(f(d), np.float64) * w))


def scipy_real_sh(d, degree: int) -> np.ndarray:
    """Real SH (jprt's convention: no Condon-Shortley phase, polar axis +Z, index l^2 + l + m)
    of unit directions d (N, 3), from SciPy's complex spherical harmonics -> (N, (degree + 1)^2).

    Numerics: not differentiable (a float64 NumPy/SciPy reference for tests).
    """
    import scipy.special as ss

    d = np.asarray(d, np.float64)
    theta = np.arccos(np.clip(d[:, 2], -1, 1))
    phi = np.arctan2(d[:, 1], d[:, 0])
    out = []
    for l in range(degree + 1):
        for m in range(-l, l + 1):
            c = ss.sph_harm_y(l, abs(m), theta, phi)
            # SciPy includes the Condon-Shortley phase (-1)^m; undo it.
            out.append(c.real if m == 0 else np.sqrt(2) * (-1) ** m * (c.real if m > 0 else c.imag))
    return np.stack(out, -1)
