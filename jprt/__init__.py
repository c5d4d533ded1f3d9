"""jprt: precomputed radiance transfer and neural global illumination in JAX."""
__version__ = "0.1.0"
