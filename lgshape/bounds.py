"""Lipschitz bounds L and G from the interval evaluators.

L bounds |grad f| over a box (the seed's space-pruning constant); G bounds
|d^T H d| = |d^2 F / dt^2| along a ray segment (the seed's monotonicity
constant for g = dF/dt). Both come from interval arithmetic on the exact
symbolic derivatives (:mod:`lgshape.expr.diff`), globally over the bounding
box or locally per cell / segment; hand-given constants are accepted instead,
as in the seed. Host-side functions here work in numpy float64.
"""
from __future__ import annotations

import numpy as np

from .arraymath import NUMPY
from .expr import evaluate_interval, gradient, hessian
from .interval import Interval, magnitude


def box_env(lo, hi) -> dict:
    """Interval variables x, y, z over boxes given as (..., 3) arrays."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    return {v: Interval(lo[..., i], hi[..., i]) for i, v in enumerate("xyz")}


def lipschitz(f, lo, hi) -> np.ndarray:
    """L >= max |grad f| over each box [lo, hi] (arrays of shape (..., 3))."""
    g = evaluate_interval(list(gradient(f)), box_env(lo, hi), NUMPY)
    L = np.sqrt(sum(magnitude(NUMPY, gi) ** 2 for gi in g))
    return np.broadcast_to(L, np.shape(lo)[:-1])


def hessian_norm(f, lo, hi) -> np.ndarray:
    """G >= max ||H||_2 over each box (Frobenius norm of interval Hessian
    entries), so |d^T H d| <= G |d|^2 for every direction d."""
    H = hessian(f)
    flat = [H[i][j] for i in range(3) for j in range(3)]
    entries = evaluate_interval(flat, box_env(lo, hi), NUMPY)
    G = np.sqrt(sum(magnitude(NUMPY, e) ** 2 for e in entries))
    return np.broadcast_to(G, np.shape(lo)[:-1])


def segment_G(h, o, d, a, b, m):
    """Local G >= max |h(t)| for t in [a, b] along o + t d, where h is the
    ray's second-derivative expression (:func:`~lgshape.expr.ray_derivatives`).
    Works on Dr.Jit or numpy arrays through the back end ``m``."""
    return magnitude(m, segment_interval(h, o, d, a, b, m))


def segment_interval(e, o, d, a, b, m) -> Interval:
    """Interval of expression e (in x, y, z, dx, dy, dz; or a list of them)
    over the ray segment o + [a, b] d. With a = b it encloses the exact value
    at that point of the ray, rounding included."""
    return evaluate_interval(e, segment_env(o, d, a, b, m), m)


def segment_env(o, d, a, b, m) -> dict:
    """Interval variables x, y, z over the segment o + [a, b] d (rounding of
    the positions included) and the plain direction dx, dy, dz."""
    env = {}
    for i, v in enumerate("xyz"):
        pa, pb = o[i] + a * d[i], o[i] + b * d[i]
        # the rounding of o + t d is relative to |o| + |t d|, not to the sum
        slack = (m.abs(o[i]) + m.maximum(m.abs(a), m.abs(b)) * m.abs(d[i])) * m.eps + m.tiny
        env[v] = Interval(m.minimum(pa, pb) - slack, m.maximum(pa, pb) + slack)
        env["d" + v] = d[i]
    return env
