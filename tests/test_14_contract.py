"""The contract for the roots of any f, and for any ray and parameter.

Oracles, per test: analytic roots (planes, spheres, ray/primitive
intersections written out below in float64), float64 polynomial roots
(lgshape.reference), and exceptions named in the docstrings. The rays are
float32; every oracle is computed in float64 from the same float32 values,
and the search's own float64 result ``t64`` is compared at the documented
tolerance (1e-6 of the box diagonal, with a factor 2 for the oracle's own
rounding)."""
import math

import numpy as np
import pytest

import drjit as dr
from conftest import JIT_AD

Array3f, Float = JIT_AD.Array3f, JIT_AD.Float

import lgshape
from lgshape.camera import primary_rays
from lgshape.reference import clip_to_box, polynomial_roots

TOL = 2e-6        # in box diagonals: the documented 1e-6, twice


def _box(h, c=(0.0, 0.0, 0.0)):
    c = np.asarray(c, np.float64)
    return tuple(c - h), tuple(c + h)


def _sphere_roots(o, d, c, r):
    """Both ray-sphere roots in float64 (NaN where the ray misses)."""
    o, d = o.astype(np.float64), d.astype(np.float64)
    oc = o - np.asarray(c, np.float64)
    a = (d * d).sum(1)
    b = (oc * d).sum(1)
    q = b * b - a * ((oc * oc).sum(1) - r * r)
    s = np.sqrt(np.where(q >= 0, q, np.nan))
    return (-b - s) / a, (-b + s) / a


def _first(roots, t0, t1):
    """The smallest root inside [t0, t1] per ray (inf where none)."""
    inside = np.isfinite(roots) & (roots >= t0[:, None]) & (roots <= t1[:, None])
    return np.where(inside, roots, np.inf).min(1)


def _compare(surf, o, d, ref, tol=TOL, grazing=None):
    """Hits exactly where the oracle has a root; t64 within tol diagonals.
    ``grazing``: rays within rounding of a tangent, where either answer is
    right (but a hit must be at the oracle's root)."""
    res = surf.trace(o, d)
    t64, hit = np.asarray(res.t64), np.asarray(res.hit)
    assert not np.asarray(res.capped).any(), f"{int(np.asarray(res.capped).sum())} rays capped"
    has = np.isfinite(ref)
    grazing = np.zeros(len(o), bool) if grazing is None else grazing
    missed = has & ~hit & ~grazing
    false = hit & ~has & ~grazing
    wrong = hit & has & ~(np.abs(t64 - ref) <= tol * surf.diagonal)
    msg = (f"rays {len(o)}, roots {int(has.sum())}, missed {int(missed.sum())}, false "
           f"{int(false.sum())}, wrong t {int(wrong.sum())} (max error "
           f"{np.nanmax(np.where(wrong, np.abs(t64 - ref), 0)) / surf.diagonal:.3g} diag)")
    assert missed.sum() == 0 and false.sum() == 0 and wrong.sum() == 0, msg
    return res


# ---------------------------------------------------------------------------
# Scale
# ---------------------------------------------------------------------------

TORUS = lambda X, Y, Z: (X**2 + Y**2 + Z**2 + 1 - 0.16)**2 - 4 * (X**2 + Y**2)  # noqa: E731


@pytest.fixture(scope="module")
def torus_rays():
    spec = lgshape.surfaces.torus()
    o, d = primary_rays(spec.bbox, 64)
    lo, hi = (np.asarray(v) for v in spec.bbox)
    t0, t1 = clip_to_box(o.astype(np.float64), d.astype(np.float64), lo, hi)
    r = polynomial_roots(TORUS, 4, o.astype(np.float64), d.astype(np.float64), t0, t1)
    real = np.where(np.abs(r.imag) < 1e-9, r.real, np.nan)
    ref = _first(real, t0, t1)
    return spec, o, d, ref


@pytest.mark.parametrize("k", [1e-30, 1e-20, 1e-12, 1e-6, 1.0, 1e6, 1e12, 1e20, 1e30])
def test01_scaled_f_has_the_same_hits(k, torus_rays):
    """k * torus has the roots of the torus (float64 polynomial roots of the
    unscaled F along each ray), for k from 1e-30 to 1e30, and the hits equal
    those of the unscaled torus."""
    spec, o, d, ref = torus_rays
    surf = lgshape.Surface(k * spec.expr, bbox=spec.bbox)
    res = _compare(surf, o, d, ref)
    base = lgshape.Surface(spec)
    assert np.array_equal(np.asarray(res.hit), np.asarray(base.trace(o, d).hit))


@pytest.mark.parametrize("k", [1e-10, 1e-12, 1e39 / 1e10])
def test02_scaled_plane(k):
    """k (x - 0.3) is hit at x = 0.3 exactly as (x - 0.3) (analytic), at the
    documented tolerance (the old absolute error floor hit 1e-10 (x - 0.3) at
    3.288 instead of 3.3)."""
    surf = lgshape.Surface(k * (lgshape.x - 0.3), bbox=_box(1.0))
    rng = np.random.default_rng(3)
    o = np.column_stack([np.full(500, -3.0), rng.uniform(-0.9, 0.9, (500, 2))]).astype(np.float32)
    d = np.column_stack([np.ones(500), rng.uniform(-0.2, 0.2, (500, 2))]).astype(np.float32)
    ref = (0.3 - o[:, 0].astype(np.float64)) / d[:, 0].astype(np.float64)
    y, z = o[:, 1] + ref * d[:, 1], o[:, 2] + ref * d[:, 2]
    ref = np.where((np.abs(y) <= 1) & (np.abs(z) <= 1), ref, np.inf)
    _compare(surf, o, d, ref)


@pytest.mark.parametrize("expr,root,h", [
    ("exp(50*x) - 2", math.log(2) / 50, 1.2),
    ("x^200 - 0.5", 0.5 ** (1 / 200), 1.2),
    ("-(x^200) + 0.5", 0.5 ** (1 / 200), 1.2),
    # beyond float32's range (1.5^400 = 1e70; exp(1000) overflows even float64,
    # where f is then infinite: no surface there)
    ("x^400 - 0.5", 0.5 ** (1 / 400), 1.5),
    ("exp(1000*x) - 2", math.log(2) / 1000, 1.2),
])
def test03_fast_growing_f(expr, root, h):
    """Fast-growing f are solved to the usual accuracy (analytic roots; rays
    along +x and -x through the box)."""
    surf = lgshape.Surface(expr, bbox=_box(h))
    rng = np.random.default_rng(4)
    n = 400
    yz = rng.uniform(-0.9 * h, 0.9 * h, (n, 2))
    o = np.concatenate([np.column_stack([np.full(n, -3.0), yz]), np.column_stack([np.full(n, 3.0), yz])])
    d = np.concatenate([np.tile([1.0, 0, 0], (n, 1)), np.tile([-1.0, 0, 0], (n, 1))])
    o, d = o.astype(np.float32), d.astype(np.float32)
    roots = np.array([root, -root]) if "^" in expr else np.array([root])   # even powers: two planes
    x_hit = np.where(d[:, 0] > 0, roots.min(), roots.max())
    ref = (x_hit - o[:, 0].astype(np.float64)) / d[:, 0]
    _compare(surf, o, d, ref)


# ---------------------------------------------------------------------------
# Domain: NaN is no surface, poles are not roots
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("expr", ["sqrt(-1 - x^2)", "1/(x - x)", "log(0*x)", "sqrt(-1 - x^2 - y^2) + z"])
def test04_f_undefined_on_the_whole_box_is_refused(expr):
    """An f that is NaN or infinite everywhere in its box is a clear error at
    construction (it used to render a solid cube)."""
    with pytest.raises(ValueError, match="NaN or infinite at all"):
        lgshape.Surface(expr, bbox=_box(1.0))


def test05_height_field_hemisphere():
    """z - sqrt(1 - x^2 - y^2) is the upper unit hemisphere: analytic
    ray-sphere roots with z >= 0; nothing outside the unit cylinder (where f
    is NaN) and nothing at the box top. Rays within 1e-6 of the rim (z = 0,
    where the surface meets the domain's edge) may go either way."""
    surf = lgshape.Surface("z - sqrt(1 - x^2 - y^2)", bbox=_box(1.5))
    o, d = primary_rays(surf.bbox, 96)
    t1, t2 = _sphere_roots(o, d, (0, 0, 0), 1.0)
    o64, d64 = o.astype(np.float64), d.astype(np.float64)
    lo, hi = surf.lo, surf.hi
    t0, te = clip_to_box(o64, d64, lo, hi)
    z1, z2 = o64[:, 2] + t1 * d64[:, 2], o64[:, 2] + t2 * d64[:, 2]
    roots = np.stack([np.where(z1 >= 0, t1, np.nan), np.where(z2 >= 0, t2, np.nan)], 1)
    ref = _first(roots, t0, te)
    rim = (np.abs(z1) < 1e-6) | (np.abs(z2) < 1e-6)
    res = _compare(surf, o, d, ref, grazing=rim)
    assert np.asarray(res.hit).sum() > 1000


def test06_pole_is_not_a_root():
    """1/x - 2 changes sign across its pole x = 0; only x = 0.5 is a root
    (analytic). Rays along +x from x = -3 cross the pole first."""
    surf = lgshape.Surface("1/x - 2", bbox=_box(1.0))
    rng = np.random.default_rng(6)
    n = 500
    o = np.column_stack([np.full(n, -3.0), rng.uniform(-0.9, 0.9, (n, 2))]).astype(np.float32)
    d = np.column_stack([np.ones(n), rng.uniform(-0.1, 0.1, (n, 2))]).astype(np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ref = (0.5 - o[:, 0].astype(np.float64)) / d[:, 0].astype(np.float64)
    p = o.astype(np.float64) + ref[:, None] * d.astype(np.float64)
    ref = np.where(np.all(np.abs(p[:, 1:]) <= 1.0, 1), ref, np.inf)
    _compare(surf, o, d, ref)
    # and from the other side, +x to -x: the root at 0.5 comes first
    o2 = o.copy()
    o2[:, 0] = 3.0
    d2 = d * np.array([-1, 1, 1], np.float32)
    ref2 = (0.5 - o2[:, 0].astype(np.float64)) / d2[:, 0].astype(np.float64)
    p2 = o2.astype(np.float64) + ref2[:, None] * d2.astype(np.float64)
    _compare(surf, o2, d2, np.where(np.all(np.abs(p2[:, 1:]) <= 1.0, 1), ref2, np.inf))


def test07_rational_pole_inside_the_box():
    """(x^2 + y^2 + z^2 - 0.5) / (x - 0.1): the sphere of radius sqrt(0.5)
    without the plane x = 0.1 (a pole). Analytic sphere roots; no hit on the
    pole plane."""
    surf = lgshape.Surface("(x^2 + y^2 + z^2 - 0.5) / (x - 0.1)", bbox=_box(1.0))
    o, d = primary_rays(surf.bbox, 64)
    t1, t2 = _sphere_roots(o, d, (0, 0, 0), math.sqrt(0.5))
    o64, d64 = o.astype(np.float64), d.astype(np.float64)
    t0, te = clip_to_box(o64, d64, surf.lo, surf.hi)
    ref = _first(np.stack([t1, t2], 1), t0, te)
    _compare(surf, o, d, ref)


# ---------------------------------------------------------------------------
# SDF primitives and CSG: no holes, no caps
# ---------------------------------------------------------------------------

def _slab(o, d, lo, hi):
    """Analytic ray/box entry (the box's surface) in float64."""
    o, d = o.astype(np.float64), d.astype(np.float64)
    t0, t1 = clip_to_box(o, d, np.asarray(lo), np.asarray(hi), t_min=-np.inf)
    inside = np.all((o >= lo) & (o <= hi), 1)
    return np.where(t0 <= t1, np.where(inside, t1, t0), np.inf), t0, t1


def test08_sdf_box_and_csg_of_boxes():
    """max(|x| - a, |y| - b, |z| - c) is the box (analytic slab test), and
    the union min(box1, box2) and the difference max(box1, -box2) of boxes
    (analytic: entry of the union = the nearer entry; for the difference,
    the first point of box1 outside box2's interior). No ray reaches the
    iteration bound."""
    from lgshape import x, y, z
    b1 = lgshape.maximum(abs(x) - 0.6, abs(y) - 0.4, abs(z) - 0.5)
    b2 = lgshape.maximum(abs(x - 0.5) - 0.3, abs(y - 0.3) - 0.3, abs(z) - 0.8)
    box = _box(1.2)
    o, d = primary_rays(box, 96)
    e1, _, _ = _slab(o, d, (-0.6, -0.4, -0.5), (0.6, 0.4, 0.5))
    e2, _, _ = _slab(o, d, (0.2, 0.0, -0.8), (0.8, 0.6, 0.8))
    # rays through an edge or corner within rounding may go either way
    _compare(lgshape.Surface(b1, bbox=box), o, d, e1)
    _compare(lgshape.Surface(lgshape.minimum(b1, b2), bbox=box), o, d, np.minimum(e1, e2))
    # difference: box1 minus box2 (camera outside both)
    _, a1, c1 = _slab(o, d, (-0.6, -0.4, -0.5), (0.6, 0.4, 0.5))
    _, a2, c2 = _slab(o, d, (0.2, 0.0, -0.8), (0.8, 0.6, 0.8))
    hit1 = a1 <= c1
    in2 = (a2 <= c2) & (a2 <= a1 + 1e-12) & (c2 > a1)     # box1's entry is inside box2
    after = np.where(hit1 & in2 & (c2 < c1), c2, np.inf)
    ref = np.where(hit1 & ~in2, a1, after)
    _compare(lgshape.Surface(lgshape.maximum(b1, -b2), bbox=box), o, d, ref)


def test09_capsule_and_cylinder():
    """A capsule (segment z in [-0.5, 0.5], radius 0.3) written with
    min/max/sqrt, and a capped cylinder max(sqrt(x^2 + y^2) - 0.5, |z| - 0.7):
    analytic ray/capsule (cylinder side + two spheres) and ray/cylinder
    (side + caps) entries."""
    o, d = primary_rays(_box(1.2), 96)
    o64, d64 = o.astype(np.float64), d.astype(np.float64)

    def side(r, zlo, zhi):
        a = d64[:, 0]**2 + d64[:, 1]**2
        b = o64[:, 0] * d64[:, 0] + o64[:, 1] * d64[:, 1]
        q = b * b - a * (o64[:, 0]**2 + o64[:, 1]**2 - r * r)
        with np.errstate(invalid="ignore", divide="ignore"):
            t = (-b - np.sqrt(q)) / a
        zt = o64[:, 2] + t * d64[:, 2]
        return np.where((q >= 0) & (zt >= zlo) & (zt <= zhi), t, np.inf)

    cap_lo = _sphere_roots(o, d, (0, 0, -0.5), 0.3)[0]
    cap_hi = _sphere_roots(o, d, (0, 0, 0.5), 0.3)[0]
    ref = np.fmin(np.fmin(side(0.3, -0.5, 0.5), np.nan_to_num(cap_lo, nan=np.inf)),
                  np.nan_to_num(cap_hi, nan=np.inf))
    capsule = lgshape.Surface("sqrt(x^2 + y^2 + (z - min(max(z, -0.5), 0.5))^2) - 0.3", bbox=_box(1.2))
    _compare(capsule, o, d, ref)

    with np.errstate(invalid="ignore", divide="ignore"):
        tc = np.stack([(s - o64[:, 2]) / d64[:, 2] for s in (-0.7, 0.7)], 1)
    xc, yc = o64[:, None, 0] + tc * d64[:, None, 0], o64[:, None, 1] + tc * d64[:, None, 1]
    caps = np.where(xc**2 + yc**2 <= 0.25, tc, np.inf).min(1)
    ref = np.fmin(side(0.5, -0.7, 0.7), caps)
    rim = np.abs(np.sqrt((o64[:, 0] + ref * d64[:, 0])**2 + (o64[:, 1] + ref * d64[:, 1])**2) - 0.5) < 1e-6
    cylinder = lgshape.Surface("max(sqrt(x^2 + y^2) - 0.5, abs(z) - 0.7)", bbox=_box(1.2))
    _compare(cylinder, o, d, ref, grazing=rim & np.isfinite(ref))


# ---------------------------------------------------------------------------
# Far from the origin
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("centre,radius", [((1e4, 1e4, 1e4), 1.0), ((1e4, -1e4, 1e4), 1e-3),
                                           ((-3e4, 2e4, 5e3), 0.25)])
def test10_far_from_the_origin(centre, radius):
    """A sphere far from the origin, written about the origin
    ((x - cx)^2 + ...), in a box tight around it: the same relative accuracy
    as near the origin (analytic ray-sphere roots in float64 from the same
    float32 rays; t64 at 2e-6 of the box diagonal)."""
    cx, cy, cz = centre
    expr = f"(x - {cx})^2 + (y - {cy})^2 + (z - {cz})^2 - {radius}^2"
    box = _box(1.5 * radius, centre)
    surf = lgshape.Surface(expr, bbox=box)
    o, d = primary_rays(box, 64)
    t1, t2 = _sphere_roots(o, d, centre, radius)
    o64, d64 = o.astype(np.float64), d.astype(np.float64)
    t0, te = clip_to_box(o64, d64, surf.lo, surf.hi)
    ref = _first(np.stack([t1, t2], 1), t0, te)
    res = _compare(surf, o, d, ref)
    assert np.asarray(res.hit).sum() > 500


# ---------------------------------------------------------------------------
# Every ray ends; inputs are checked
# ---------------------------------------------------------------------------

def test11_degenerate_rays_are_misses_and_end():
    """Zero, infinite and NaN directions, and NaN origins, are misses; they
    end (0 capped) whatever the origin, and do not hold up the other rays
    of the batch (a normal ray in the batch still hits at its analytic
    root, 2)."""
    surf = lgshape.Surface("x^2 + y^2 + z^2 - 1", bbox=_box(1.5))
    inf, nan = math.inf, math.nan
    o = np.array([[0, 0, 0], [0.2, 0.1, 0], [0, 0, -3], [0, 0, -3], [0, 0, 0], [nan, 0, -3],
                  [0, 0, -3]], np.float32)
    d = np.array([[0, 0, 0], [inf, 0, 0], [0, inf, 1], [nan, 0, 1], [0, 0, nan], [0, 0, 1],
                  [0, 0, 1]], np.float32)
    res = surf.trace(o, d)
    hit = np.asarray(res.hit)
    assert not hit[:6].any() and np.all(np.isinf(np.asarray(res.t)[:6]))
    assert not np.asarray(res.capped).any()
    assert hit[6] and abs(float(np.asarray(res.t64)[6]) - 2.0) <= TOL * surf.diagonal


def test12_inputs_are_checked():
    """(N, 3) arrays or Array3f; one ray as (3,); a (3, N) array is refused
    (it would be read as other rays); empty input gives empty output;
    mismatched sizes name both."""
    surf = lgshape.Surface("x^2 + y^2 + z^2 - 1", bbox=_box(1.5))
    o = np.array([[0, 0, -3]] * 5, np.float32)
    d = np.array([[0, 0, 1]] * 5, np.float32)
    t, hit = surf.intersect(o, d)
    assert np.asarray(hit).all()
    t1, hit1 = surf.intersect(o[0], d[0])
    assert dr.width(t1) == 1 and np.asarray(hit1)[0]
    with pytest.raises(ValueError, match=r"\(N, 3\).*transposed"):
        surf.intersect(o.T, d.T)
    with pytest.raises(ValueError, match="mismatched sizes.*4.*5|mismatched sizes.*5.*4"):
        surf.intersect(o[:4], d)
    with pytest.raises(ValueError, match="mismatched sizes"):
        surf.intersect(o, d, t_max=Float(np.ones(3)))
    t0, h0 = surf.intersect(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32))
    assert dr.width(t0) == 0 and dr.width(h0) == 0
    te, he = surf.intersect(Array3f(), Array3f())
    assert dr.width(te) == 0
    # one origin, many directions: broadcast
    t2, h2 = surf.intersect(o[:1], d)
    assert dr.width(t2) == 5 and np.asarray(h2).all()


def test13_parameters_are_checked():
    """depth must be an integer in 2..10; the box finite with min < max; a
    hand-given L or G is checked against sampled |grad f| (resp. the
    Hessian's norm) and refused with the point that violates it; a valid one
    is accepted. Oracle: for the unit sphere |grad f| = 2|p| (largest at a
    box corner, 2 sqrt(3) * 1.5) and the Hessian is 2 I."""
    sphere = "x^2 + y^2 + z^2 - 1"
    with pytest.raises(ValueError, match="depth must be an integer"):
        lgshape.Surface(sphere, bbox=_box(1.5), depth=2.7)
    with pytest.raises(ValueError, match="depth must be between"):
        lgshape.Surface(sphere, bbox=_box(1.5), depth=12)
    with pytest.raises(ValueError, match="finite"):
        lgshape.Surface(sphere, bbox=((-1, -1, -math.inf), (1, 1, 1)))
    with pytest.raises(ValueError, match="min < max"):
        lgshape.Surface(sphere, bbox=((1, -1, -1), (-1, 1, 1)))
    L_true = 2 * math.sqrt(3) * 1.5
    with pytest.raises(ValueError, match=r"L = 1.0 is too small: \|grad f\| = .* at \("):
        lgshape.Surface(sphere, bbox=_box(1.5), L=1.0)
    assert lgshape.Surface(sphere, bbox=_box(1.5), L=L_true * 1.0001).L > 0
    with pytest.raises(ValueError, match=r"G = 1.5 is too small.*reaches 2 "):
        lgshape.Surface(sphere, bbox=_box(1.5), G=1.5)
    assert lgshape.Surface(sphere, bbox=_box(1.5), G=2.0).search == "global"
    with pytest.raises(ValueError, match="max_iterations must be an integer"):
        lgshape.Surface(sphere, bbox=_box(1.5), max_iterations=10.5)
