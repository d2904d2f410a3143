"""Lipschitz bounds L (per box) and G (per ray segment, and global).

Oracle: brute-force sampling. |grad f| sampled inside a box never exceeds
the box's L; |d^T H d| sampled along a segment never exceeds its G; the
global G bounds |d^T H d| for unit directions anywhere in the box."""
import numpy as np
import pytest
from conftest import SURFACE_NAMES, random_boxes

from conftest import JIT

Float = JIT.Float

from lgshape import bounds
from lgshape.arraymath import NUMPY, DrJitMath
from lgshape.expr import evaluate, gradient, ray_derivatives
from lgshape.surfaces import LIBRARY


@pytest.mark.parametrize("name", SURFACE_NAMES)
def test01_L_bounds_sampled_gradient(name, rng):
    s = LIBRARY[name]()
    lo, hi = random_boxes(rng, s.bbox, 300)
    L = bounds.lipschitz(s.expr, lo, hi)
    P = lo[:, None] + (hi - lo)[:, None] * rng.uniform(0, 1, (300, 50, 3))
    g = evaluate(list(gradient(s.expr)), {v: P[..., i] for i, v in enumerate("xyz")})
    norm = np.sqrt(sum(np.broadcast_to(gi, P.shape[:2]) ** 2 for gi in g))
    assert np.all(norm <= L[:, None])
    # and the bound is informative, not infinite
    assert np.all(np.isfinite(L))


@pytest.mark.parametrize("name", SURFACE_NAMES)
def test02_G_bounds_sampled_dhd(name, rng):
    s = LIBRARY[name]()
    n = 1000
    lo, hi = np.asarray(s.bbox[0]), np.asarray(s.bbox[1])
    o = lo + (hi - lo) * rng.uniform(0, 1, (n, 3))
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    a = np.zeros(n)
    b = rng.uniform(0.01, 0.5, n)
    _, h = ray_derivatives(s.expr)
    for m, conv in ((NUMPY, np.asarray), (DrJitMath(Float), Float)):
        G = bounds.segment_G(h, [conv(o[:, i]) for i in range(3)], [conv(d[:, i]) for i in range(3)],
                             conv(a), conv(b), m)
        G = np.broadcast_to(np.asarray(G, np.float64), (n,))
        t = b[:, None] * rng.uniform(0, 1, (n, 40))
        env = {v: o[:, None, i] + t * d[:, None, i] for i, v in enumerate("xyz")}
        env.update({"d" + v: d[:, None, i] for i, v in enumerate("xyz")})
        hv = np.abs(np.broadcast_to(evaluate(h, env), t.shape))
        assert np.all(hv <= G[:, None])


@pytest.mark.parametrize("name", SURFACE_NAMES)
def test03_global_G(name, rng):
    s = LIBRARY[name]()
    lo, hi = np.asarray(s.bbox[0]), np.asarray(s.bbox[1])
    G = bounds.hessian_norm(s.expr, lo[None], hi[None])[0]
    P = lo + (hi - lo) * rng.uniform(0, 1, (20000, 3))
    d = rng.normal(size=P.shape)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    _, h = ray_derivatives(s.expr)
    env = {v: P[:, i] for i, v in enumerate("xyz")}
    env.update({"d" + v: d[:, i] for i, v in enumerate("xyz")})
    assert np.all(np.abs(evaluate(h, env)) <= G)
