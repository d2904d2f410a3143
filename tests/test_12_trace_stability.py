"""Where sampling methods fail: thin spikes, thin shells, surfaces through
grid vertices, ray origins on the surface, singular points.

Oracles, all in float64 on the same float32 rays the kernel sees, at the
documented tolerance (|t64 - r| <= 1e-6 x diag / |d|, see
:mod:`oracles`):
- spikes: the analytic spike geometry (every test ray crosses a spike axis,
  where f < 0 by construction), and the first root from a float64 scan of
  f written out from :func:`lgshape.surfaces.spikes`'s formula, at a step
  far below the spikes' widths, bisected;
- thin shells: both spheres' roots in closed form;
- the sphere, torus, plane and cone of the other tests: closed forms or
  companion-matrix roots (:func:`lgshape.reference.polynomial_roots`), held by
  :func:`oracles.check_first_roots` (the rules of test_11);
- termination: the iteration bound (no ray may reach it)."""
import math

import numpy as np
import pytest

import lgshape
from lgshape import parse
from lgshape.bench import baselines
from lgshape.expr import evaluate, gradient, hessian
from lgshape.reference import clip_to_box, first_sign_change, polynomial_roots
from lgshape.surfaces import SPIKE_AXES
from oracles import check_first_roots, sphere_roots

_AXES = np.asarray(SPIKE_AXES, float) / np.linalg.norm(np.asarray(SPIKE_AXES, float), axis=1)[:, None]


def spikes_f(X, Y, Z, core=0.5, height=1.0, width=0.01):
    """The spikes' f in float64, from its formula (independent of the DAG):
    |p|^2 - core^2 - height * sum_k exp(-|p x a_k|^2 / width^2)."""
    s = 0.0
    for a in _AXES:
        cx, cy, cz = a[1] * Z - a[2] * Y, a[2] * X - a[0] * Z, a[0] * Y - a[1] * X
        s = s + np.exp(-(cx * cx + cy * cy + cz * cz) / width**2)
    return X * X + Y * Y + Z * Z - core**2 - height * s


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


@pytest.mark.parametrize("depth", [6, None])
def test01_every_spike_is_hit(depth, rng):
    """Every ray crossing a spike hits the first root of its float64 scan at
    the documented tolerance (on t64), as a resolved simple root (at depth 6
    and at the default depth: the spikes are thinner than a cell in both)."""
    spec = lgshape.surfaces.spikes()
    surf = lgshape.Surface(spec, depth=depth)
    o, d = spike_rays(rng)
    cell = float(np.min(surf.grid.cell_size))
    cell6 = float(np.min(np.subtract(*spec.bbox[::-1]))) / 2 ** 6
    # Oracle: f < 0 on the spike axis by construction (checked), and a fine
    # float64 scan confirms a sign change near the crossing.
    F = spikes_f
    o64, d64 = o.astype(np.float64), d.astype(np.float64)
    axis_pts = o64 + 2.0 * d64
    assert np.all(F(*axis_pts.T) < 0)
    assert np.allclose(F(*axis_pts.T), evaluate(spec.expr, dict(zip("xyz", axis_pts.T))), rtol=1e-12, atol=1e-12)
    t_axis = first_sign_change(F, o64, d64, np.full(len(o), 1.9), np.full(len(o), 2.1), steps=20000)
    assert np.all(np.isfinite(t_axis))
    # Spike half-width at the test heights: thinner than a grid cell.
    width = 2.0 - t_axis
    assert np.all(width < cell)
    # The nearest root (the ray may cross another spike first): float64 scan
    # at a step of 2e-5, far below the spikes' widths here, bisected to
    # float64 precision.
    t_ref = np.concatenate([first_sign_change(F, o64[k:k + 48], d64[k:k + 48], np.zeros(48),
                                              t_axis[k:k + 48] + 1e-3, steps=100_000, bisections=60)
                            for k in range(0, len(o), 48)])
    r = surf.trace(o, d)
    hit, t64 = np.asarray(r.hit), np.asarray(r.t64)
    assert not np.asarray(r.capped).any()
    assert hit.all(), f"{(~hit).sum()} of {len(o)} spike rays missed"
    assert np.array_equal(np.asarray(r.t), t64.astype(np.float32))
    tol = 1e-6 * surf.diagonal / np.linalg.norm(d64, axis=1)
    err = np.abs(t64 - t_ref)
    assert np.all(err <= tol), (f"{(err > tol).sum()} rays off the first root; max depth error "
                                f"{err.max() / surf.diagonal:.2e} x diag at ray {err.argmax()}")
    # A spike crossing is a steep simple root: the monotonicity test proves it.
    assert not np.asarray(r.unresolved).any(), f"{np.asarray(r.unresolved).sum()} unresolved"

    # A fixed-step marcher with the depth-6 grid's step misses many of them:
    # the failure the method exists to prevent.
    m = baselines.march(surf, o, d, step=cell6)
    assert (~np.asarray(m.hit)).sum() > len(o) // 4


def _assert_terminates(res, n):
    capped = int(np.asarray(res.capped).sum())
    assert capped == 0, f"{capped} of {n} rays reached the iteration bound"


TORUS_F = (4, lambda X, Y, Z: (X**2 + Y**2 + Z**2 + 1 - 0.16)**2 - 4 * (X**2 + Y**2))


def _roots(name, o32, d32, surf, t_min=0.0):
    """All roots along the float32 rays: closed form for the unit sphere,
    companion matrix for the torus."""
    o, d = o32.astype(np.float64), d32.astype(np.float64)
    if name == "sphere":
        return lambda X, Y, Z: X**2 + Y**2 + Z**2 - 1, sphere_roots(o, d, (0, 0, 0), 1.0)
    degree, F = TORUS_F
    t0, t1 = clip_to_box(o, d, surf.lo, surf.hi, t_min)
    return F, polynomial_roots(F, degree, o, d, t0, t1)


def test02_origin_on_the_surface(rng):
    """Rays leaving from points on the sphere and the torus (inward, outward,
    tangent), t_min = 0: all finish, and their hits follow the first-root
    rules of test_11 against closed-form (sphere) or companion-matrix
    (torus) roots; the root at the origin (within float32 rounding of t = 0)
    is the allowed ambiguity there. With t_min = 1e-3 every inward ray finds
    the far side at its root."""
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
        p32 = p.astype(np.float32)
        for label, d in (("inward", -n), ("outward", n), ("tangent", np.cross(n, rng.normal(size=n.shape)))):
            d32 = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
            res = surf.trace(p32, d32)
            _assert_terminates(res, len(p))
            F, roots = _roots(spec.name, p32, d32, surf)
            check_first_roots(surf, F, p32, d32, roots, res=res, groups=np.repeat([label], len(p)))
        d32 = (-n).astype(np.float32)
        F, roots = _roots(spec.name, p32, d32, surf, t_min=1e-3)
        counts = check_first_roots(surf, F, p32, d32, roots, t_min=1e-3)
        # Every inward ray has a verified far-side root, and so a hit there.
        assert counts["simple"] + counts["faint"] == len(p), counts


def test03_grid_vertices_on_the_surface(rng):
    """Surfaces through grid vertices: the plane x = 0.25 and the sphere of
    radius 0.5 in [-1, 1]^3 (vertex spacing 1/32), rays along grid lines
    through vertices. Oracles: the plane's root (0.25 - o_x) / d_x; the
    sphere's roots in closed form, under test_11's rules (a ray along a grid
    line at distance 0.5 from the centre touches the sphere at a vertex: a
    double root, the allowed ambiguity)."""
    k = rng.integers(-32, 33, (2000, 3)) / 32
    o = k.copy()
    o[:, 0] = -2.0
    d = np.tile([1.0, 0.0, 0.0], (len(o), 1))
    o32, d32 = o.astype(np.float32), d.astype(np.float32)
    plane = lgshape.Surface("x - 0.25", bbox=((-1, -1, -1), (1, 1, 1)))
    res = plane.trace(o32, d32)
    _assert_terminates(res, len(o))
    root = (0.25 - o[:, 0]) / d[:, 0]
    assert np.asarray(res.hit).all()
    assert np.all(np.abs(np.asarray(res.t64) - root) <= 1e-6 * plane.diagonal)
    ball = lgshape.Surface("x^2 + y^2 + z^2 - 0.25", bbox=((-1, -1, -1), (1, 1, 1)))
    res = ball.trace(o32, d32)
    _assert_terminates(res, len(o))
    counts = check_first_roots(ball, lambda X, Y, Z: X**2 + Y**2 + Z**2 - 0.25, o32, d32,
                               sphere_roots(o32, d32, (0, 0, 0), 0.5), res=res)
    assert counts["simple"] > 300 and counts["none"] > 300, counts


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
    polynomial roots along each (float32) ray (test_11's rules: every
    verified first root found at its t64 within 1e-6 x diag, no hit away
    from the first root). Through a node F has a double root, so the float32
    ray, which passes within rounding of the node, has two close roots or
    none: either answer is right there (the near-tangent allowance, not
    bounded here: the first root is the node itself on most rays), but a hit
    must be at the node or at the first verified root."""
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
               groups=np.repeat(["node"], len(o)), min_simple=-1, tangent_max=None)


SHELL_BOX = ((-1.2, -1.2, -1.2), (1.2, 1.2, 1.2))
SHELL_W = 1e-5 * 2.4 * math.sqrt(3)        # 1e-5 x the box diagonal


@pytest.mark.parametrize("form", ["product", "abs"])
def test06_thin_shell(form, rng):
    """A spherical shell 1e-5 x the box diagonal thick, between the spheres
    of radius 1 and 1 + w: f = (|p|^2 - 1)(|p|^2 - (1 + w)^2) (a product of
    level sets) or | |p| - 1 - w/2 | - w/2 (abs and sqrt). 3000 rays from
    outside the box aimed at points inside the inner sphere: each crosses
    the shell, so its first two roots (outer, then inner sphere) are at
    least w apart. Oracle: both spheres' roots in closed form; every ray
    must hit at the outer sphere's entry, |t64 - r| <= 1e-6 x diag (under
    test_11's rules they are all in the ``pair`` class). A bisection depth
    bound too low for the shell leaves a minimum-width interval holding
    both roots, with one sign at its ends: the ray misses."""
    r2 = "x^2 + y^2 + z^2"
    R2 = 1.0 + SHELL_W
    if form == "product":
        text = f"({r2} - 1) * ({r2} - {R2 * R2!r})"

        def F(X, Y, Z):
            q = X * X + Y * Y + Z * Z
            return (q - 1) * (q - R2 * R2)
    else:
        text = f"abs(sqrt({r2}) - {1 + SHELL_W / 2!r}) - {SHELL_W / 2!r}"

        def F(X, Y, Z):
            return np.abs(np.sqrt(X * X + Y * Y + Z * Z) - (1 + SHELL_W / 2)) - SHELL_W / 2
    surf = lgshape.Surface(parse(text), bbox=SHELL_BOX)
    assert abs(SHELL_W - 1e-5 * surf.diagonal) < 1e-15
    n = 3000
    u = rng.normal(size=(n, 3))
    o = 3.0 * u / np.linalg.norm(u, axis=1, keepdims=True)
    target = rng.normal(size=(n, 3))
    target *= (0.999 * rng.uniform(0, 1, (n, 1)) ** (1 / 3)) / np.linalg.norm(target, axis=1, keepdims=True)
    d = target - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o32, d32 = o.astype(np.float32), d.astype(np.float32)
    roots = np.concatenate([sphere_roots(o32, d32, (0, 0, 0), R2),
                            sphere_roots(o32, d32, (0, 0, 0), 1.0)], 1)
    res = surf.trace(o32, d32)
    _assert_terminates(res, n)
    hit = np.asarray(res.hit)
    assert hit.all(), f"{(~hit).sum()} of {n} rays through the shell missed it"
    counts = check_first_roots(surf, F, o32, d32, roots, res=res)
    assert counts["pair"] == n, counts


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
