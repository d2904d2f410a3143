"""Where sampling methods fail: thin spikes, surfaces through grid vertices,
ray origins on the surface, singular points.

Oracles: for the spikes, the analytic spike geometry (every test ray crosses a
spike axis, where f < 0 by construction) cross-checked by float64 brute-force
sampling at a step 1000x finer than the spike; for termination, the
iteration bound (no ray may reach it) and float64 values of f at the hits."""
import numpy as np

import lgshape
from lgshape import baselines, parse
from lgshape.expr import evaluate, gradient, hessian
from lgshape.reference import first_sign_change
from lgshape.surfaces import SPIKE_AXES


def _perp(a, rng):
    u = np.cross(a, rng.normal(size=3))
    return u / np.linalg.norm(u)


def spike_rays(rng, heights=(0.6, 0.8, 0.95, 1.05), per=6):
    """Rays crossing each of the 14 spikes perpendicularly at several heights
    (|p| up to 1.05 of the tip at sqrt(1.25) = 1.118)."""
    o, d = [], []
    for axis in SPIKE_AXES:
        a = np.asarray(axis, float) / np.linalg.norm(axis)
        for sign in (1, -1):
            for h in heights:
                for _ in range(per):
                    u = _perp(a, rng)
                    p = sign * h * a
                    o.append(p + 2.0 * u)
                    d.append(-u)
    return np.asarray(o, np.float32), np.asarray(d, np.float32)


def test01_every_spike_is_hit(rng):
    spec = lgshape.surfaces.spikes()
    surf = lgshape.Surface(spec)
    o, d = spike_rays(rng)
    cell = float(np.min(surf.grid.cell_size))
    # Oracle: f < 0 on the spike axis by construction (checked), and a fine
    # float64 scan confirms a sign change near the crossing.
    F = lambda X, Y, Z: evaluate(spec.expr, {"x": X, "y": Y, "z": Z})  # noqa: E731
    axis_pts = o.astype(np.float64) + 2.0 * d.astype(np.float64)
    assert np.all(F(*axis_pts.T) < 0)
    o64, d64 = o.astype(np.float64), d.astype(np.float64)
    t_axis = first_sign_change(F, o64, d64, np.full(len(o), 1.9), np.full(len(o), 2.1), steps=20000)
    assert np.all(np.isfinite(t_axis))
    # Spike half-width at the test heights: thinner than a grid cell.
    width = 2.0 - t_axis
    assert np.all(width < cell)
    # The nearest root (the ray may cross another spike first): float64 scan
    # at a step of 2e-5, far below the spikes' widths here.
    t_ref = np.concatenate([first_sign_change(F, o64[k:k + 48], d64[k:k + 48], np.zeros(48),
                                              t_axis[k:k + 48] + 1e-3, steps=100_000)
                            for k in range(0, len(o), 48)])
    r = surf.trace(o, d)
    t = np.asarray(r.t)
    assert np.asarray(r.hit).all(), f"{(~np.asarray(r.hit)).sum()} of {len(o)} spike rays missed"
    err = np.abs(t - t_ref)
    assert np.all(err < 1e-4 * surf.diagonal), f"max depth error {err.max():.2e} at ray {err.argmax()}"
    assert not np.asarray(r.capped).any()

    # A fixed-step marcher with the grid's step misses many of them: the
    # failure the method exists to prevent.
    m = baselines.march(surf, o, d, step=cell)
    assert (~np.asarray(m.hit)).sum() > len(o) // 4


def _assert_terminates(res, n):
    capped = int(np.asarray(res.capped).sum())
    assert capped == 0, f"{capped} of {n} rays reached the iteration bound"


def test02_origin_on_the_surface(rng):
    """Rays leaving from points on the sphere and the torus (inward, outward,
    tangent), t_min = 0: all finish; a ray that heads into the solid finds the
    far side."""
    for spec in (lgshape.surfaces.sphere(), lgshape.surfaces.torus()):
        surf = lgshape.Surface(spec)
        # surface points: project random points with Newton along the gradient
        p = rng.normal(size=(3000, 3))
        p = p / np.linalg.norm(p, axis=1, keepdims=True)
        g = gradient(spec.expr)
        for _ in range(30):
            env = dict(zip("xyz", p.T))
            fv = evaluate(spec.expr, env)
            gv = np.stack([np.broadcast_to(v, len(p)) for v in evaluate(list(g), env)], 1)
            p = p - (fv / np.maximum((gv ** 2).sum(1), 1e-12))[:, None] * gv
        n = gv / np.linalg.norm(gv, axis=1, keepdims=True)
        for d in (-n, n, np.cross(n, rng.normal(size=n.shape))):
            d = d / np.linalg.norm(d, axis=1, keepdims=True)
            res = surf.trace(p.astype(np.float32), d.astype(np.float32))
            _assert_terminates(res, len(p))
        inward = surf.trace(p.astype(np.float32), (-n).astype(np.float32), t_min=1e-3)
        t = np.asarray(inward.t)
        assert np.asarray(inward.hit).mean() > 0.99
        q = p - t[:, None] * n
        hit = np.asarray(inward.hit)
        assert np.all(np.abs(evaluate(spec.expr, dict(zip("xyz", q[hit].T)))) < 1e-3)


def test03_grid_vertices_on_the_surface(rng):
    """Surfaces through grid vertices: the plane x = 0.25 and the sphere of
    radius 0.5 in [-1, 1]^3 (vertex spacing 1/32)."""
    for text, root in (("x - 0.25", lambda o, d: (0.25 - o[:, 0]) / d[:, 0]), ("x^2 + y^2 + z^2 - 0.25", None)):
        surf = lgshape.Surface(text, bbox=((-1, -1, -1), (1, 1, 1)))
        # rays along grid lines through vertices
        k = rng.integers(-32, 33, (2000, 3)) / 32
        o = k.copy()
        o[:, 0] = -2.0
        d = np.tile([1.0, 0.0, 0.0], (len(o), 1))
        res = surf.trace(o.astype(np.float32), d.astype(np.float32))
        _assert_terminates(res, len(o))
        if root is not None:
            assert np.asarray(res.hit).all()
            assert np.allclose(np.asarray(res.t), root(o, d), atol=1e-5)


def _critical_points(expr, bbox, rng, n=20000):
    """Points where grad f = 0 on f = 0, by Newton on grad f from the grid
    samples with the smallest |grad f| + |f| (exact Hessian)."""
    lo, hi = np.asarray(bbox[0]), np.asarray(bbox[1])
    p = lo + (hi - lo) * rng.uniform(0, 1, (n, 3))
    g, H = gradient(expr), hessian(expr)

    def grad_hess(p):
        env = dict(zip("xyz", p.T))
        gv = np.stack([np.broadcast_to(v, len(p)) for v in evaluate(list(g), env)], 1)
        Hv = np.stack([np.stack([np.broadcast_to(v, len(p)) for v in evaluate(list(row), env)], 1)
                       for row in H], 1)
        return gv, Hv
    gv, _ = grad_hess(p)
    fv = np.abs(evaluate(expr, dict(zip("xyz", p.T))))
    p = p[np.argsort(np.linalg.norm(gv, axis=1) + fv)[:400]]
    for _ in range(40):
        gv, Hv = grad_hess(p)
        p = p - np.linalg.solve(Hv + 1e-12 * np.eye(3), gv[..., None])[..., 0]
    fv = evaluate(expr, dict(zip("xyz", p.T)))
    gv, _ = grad_hess(p)
    ok = (np.abs(fv) < 1e-9) & (np.linalg.norm(gv, axis=1) < 1e-9) & np.all((p > lo) & (p < hi), axis=1)
    return np.unique(np.round(p[ok], 9), axis=0)


def test04_singular_points(rng):
    """Rays through the Kummer surface's nodes and the apex of the cone
    x^2 + y^2 - z^2 finish, and their hits are those of the float64
    polynomial roots along each (float32) ray (test_11's oracle: every simple
    first root found at its t, no hit without a root within delta). Through
    a node F has a double root, so the float32 ray, which passes within
    rounding of the node, has two close roots or none: either answer is
    right there (the first root is the node itself on most rays, so few are
    simple), but a hit must be at a root."""
    from test_11_trace_oracle import FORMULAS, _check
    kummer = lgshape.surfaces.kummer()
    nodes = _critical_points(kummer.expr, kummer.bbox, rng)
    assert len(nodes) >= 4
    cone = lgshape.surfaces.Implicit("cone", parse("x^2 + y^2 - z^2"), ((-1,) * 3, (1,) * 3))
    cases = [(kummer, nodes, FORMULAS["kummer"]),
             (cone, np.zeros((1, 3)), (2, lambda X, Y, Z: X**2 + Y**2 - Z**2))]
    for spec, pts, (degree, F) in cases:
        surf = lgshape.Surface(spec)
        d = rng.normal(size=(len(pts) * 500, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        through = np.repeat(pts, 500, axis=0)
        o = through - 3.0 * d
        res = surf.trace(o.astype(np.float32), d.astype(np.float32))
        _assert_terminates(res, len(o))
        _check(surf, F, degree, o.astype(np.float32), d.astype(np.float32),
               groups=np.repeat(["node"], len(o)), min_simple=-1, noise_max=0.0)


def test05_rays_at_the_bound_are_reported(rng):
    """With a tiny iteration bound the capped rays are counted and reported as
    misses, never as hits."""
    spec = lgshape.surfaces.chmutov6()
    surf = lgshape.Surface(spec, max_iterations=3)
    from lgshape.camera import primary_rays
    o, d = primary_rays(spec.bbox, 64)
    res = surf.trace(o, d)
    capped = np.asarray(res.capped)
    assert capped.sum() > 100
    assert not np.asarray(res.hit)[capped].any()
    assert np.all(np.isinf(np.asarray(res.t)[capped]))
