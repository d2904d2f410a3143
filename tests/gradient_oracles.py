"""Finite-difference oracles and per-seed gradient estimates shared by the
gradient tests: the image mean in float64, lg_prb's forward-mode estimates
of d mean / d params[key] over independent seeds, and central differences
of a primal integrator's image mean at the same seed on both sides; and
the diffuse lgsurface ball their scenes move."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np


def image_mean(img) -> float:
    return float(np.mean(np.array(img, np.float64)))


def mean_and_se(values):
    values = np.asarray(values, np.float64)
    return float(values.mean()), float(values.std(ddof=1) / np.sqrt(len(values)))


def forward_estimates(scene, key, seeds, seed=5):
    """d mean / d params[key] by the scene's integrator in forward mode, one
    estimate per seed pair (seed + 2k, seed + 2k + 1): an array."""
    params = mi.traverse(scene)
    out = []
    for k in range(seeds):
        dr.enable_grad(params[key])
        params.update()
        img = mi.render(scene, params, seed=seed + 2 * k, seed_grad=seed + 2 * k + 1)
        dr.forward(params[key])
        out.append(image_mean(dr.grad(img)))
    return np.array(out)


def central_difference(make, value, h, seeds, seed=100):
    """(mean, SE) over ``seeds`` seeds of (m(value + h) - m(value - h)) / 2h,
    m the image mean of ``make(v)``'s scene rendered at the same seed on both
    sides."""
    out = []
    for k in range(seeds):
        a = image_mean(mi.render(make(value + h), seed=seed + k))
        b = image_mean(mi.render(make(value - h), seed=seed + k))
        out.append((a - b) / (2 * h))
    return mean_and_se(out)


def diffuse_ball(r, at, rho, half=0.6):
    """A diffuse lgsurface sphere of radius ``r`` (its parameter ``r``) at
    ``at``, in a fixed box of half-size ``half``."""
    return {"type": "lgsurface", "expr": "x^2 + y^2 + z^2 - r^2", "r": r,
            "bbox_min": [-half] * 3, "bbox_max": [half] * 3,
            "to_world": mi.ScalarTransform4f().translate(list(at)),
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": rho}}}
