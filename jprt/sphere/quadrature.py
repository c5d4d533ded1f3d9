"""Reference spherical quadrature in NumPy float64: polar grids dense around a pole, for checking
closed forms of sharp lobes (SG integrals, products, convolutions) in tests and benchmarks."""

import numpy as np


def frame(axis):
    axis = np.asarray(axis, np.float64)
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, axis)
    x /= np.linalg.norm(x)
    return x, np.cross(axis, x)


def polar_grid(pole, n_theta=1500, n_phi=400):
    """Directions and solid-angle weights of a polar grid around ``pole`` with theta = pi t^2,
    dense near the pole (where sharp lobes centred there live)."""
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
    d, w = polar_grid(pole, **grid)
    return float(np.sum(np.asarray(f(d), np.float64) * w))
