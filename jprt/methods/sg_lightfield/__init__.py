"""Spherical-Gaussian light-field textures (Currius et al. 2020): ``model`` (lobes, constraints,
the log-L2 loss, the CNN encoder's training, the run-time shading; pure JAX). The light-field
capture it fits is ``jprt.render.lightfield``. Not registered in ``jprt.methods.REGISTRY`` yet:
the dataset, the baselines, environment visibility and the experiment are still to come."""

from jprt.methods.sg_lightfield import model

__all__ = ["model"]
