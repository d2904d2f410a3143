"""Quadratic forms along ray segments (lgshape.expr.quadratic): sound for
every op and library surface, exact on quadratics, third order on
polynomials.

Oracles: float64 point values at sampled points of each segment (ends
included) must lie inside the form's range, computed both in numpy float64
and in Dr.Jit float32, with no tolerance; the analytic range of a quadratic
in t (its values at the ends and at its vertex); the sampled range for the
order of the excess."""
import numpy as np
import pytest
from conftest import ALL_CASES, case_expr, case_id
from oracles import assert_inside

from conftest import JIT

Float = JIT.Float

from lgshape.arraymath import NUMPY, DrJitMath
from lgshape.bounds import segment_env
from lgshape.expr import evaluate, evaluate_interval, parse, ray_derivatives
from lgshape.expr.quadratic import (Quad, Segment, coordinate, evaluate_quadratic, quad_clip,
                                    quad_ends, quad_env, quad_range)
from lgshape.interval import Interval

SEGMENTS, SAMPLES = 2000, 33


def _segments(rng, bbox, n, scale=0.3):
    lo, hi = np.asarray(bbox[0]), np.asarray(bbox[1])
    o = lo + (hi - lo) * rng.uniform(0, 1, (n, 3))
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    a = rng.uniform(-0.5, 0.5, n)
    b = a + np.linalg.norm(hi - lo) * rng.uniform(1e-4, scale, n) ** 2
    return o, d, a, b


def _ranges(exprs, o, d, a, b, backend):
    """Ranges of the forms of exprs over the segments o + [a, b] d."""
    if backend == "numpy64":
        m = NUMPY
        seg, env = quad_env(m, list(o.T), list(d.T), a, b)
        out = [quad_range(seg, q) for q in evaluate_quadratic(exprs, env, seg)]
        n = len(a)
        return [(np.broadcast_to(r.lo, (n,)), np.broadcast_to(r.hi, (n,))) for r in out]
    m = DrJitMath(Float)
    O, D = [Float(o[:, i]) for i in range(3)], [Float(d[:, i]) for i in range(3)]
    seg, env = quad_env(m, O, D, Float(a), Float(b))
    out = [quad_range(seg, q) for q in evaluate_quadratic(exprs, env, seg)]
    z = 0 * O[0]
    return [(np.asarray(r.lo + z, np.float64), np.asarray(r.hi + z, np.float64)) for r in out]


def _values(e, o, d, t):
    env = {v: o[:, None, i] + t * d[:, None, i] for i, v in enumerate("xyz")}
    env.update({"d" + v: d[:, None, i] for i, v in enumerate("xyz")})
    return np.broadcast_to(evaluate(e, env), t.shape)


@pytest.mark.parametrize("backend", ["numpy64", "drjit32"])
@pytest.mark.parametrize("case", ALL_CASES, ids=case_id)
def test01_segment_soundness(case, backend, rng):
    """f and g = dF/dt over random segments (lengths 1e-8 to 0.09 of the
    box diagonal): every sampled float64 value inside the range, NaN
    (undefined points) excepted. No tolerance."""
    f, bbox = case_expr(*case)
    g, _ = ray_derivatives(f)
    if backend == "drjit32":
        # the float32 forms enclose the ray with float32 ends: sample that ray
        o, d, a, b = (v.astype(np.float32).astype(np.float64)
                      for v in _segments(rng, bbox, SEGMENTS))
    else:
        o, d, a, b = _segments(rng, bbox, SEGMENTS)
    t = a[:, None] + (b - a)[:, None] * np.linspace(0, 1, SAMPLES)[None]
    for name, e, (lo, hi) in zip(("f", "g"), (f, g), _ranges([f, g], o, d, a, b, backend)):
        assert_inside(name, lo[:, None], hi[:, None], _values(e, o, d, t))


@pytest.mark.parametrize("backend", ["numpy64", "drjit32"])
@pytest.mark.parametrize("case", ALL_CASES, ids=case_id)
def test01b_end_values_sound(case, backend, rng):
    """The bounds of f at the segment's ends (``quad_ends``: the form at
    s = -r and s = +r, which the search uses for the signs at an interval's
    ends): the float64 value of f at tm -+ r (tm and r as the form has them)
    inside them, NaN (undefined points) excepted. No tolerance."""
    f, bbox = case_expr(*case)
    if backend == "drjit32":
        o, d, a, b = (v.astype(np.float32).astype(np.float64)
                      for v in _segments(rng, bbox, SEGMENTS))
        m = DrJitMath(Float)
        O, D = [Float(o[:, i]) for i in range(3)], [Float(d[:, i]) for i in range(3)]
        A, B = Float(a), Float(b)
        seg, env = quad_env(m, O, D, A, B)
        (q,) = evaluate_quadratic([f], env, seg)
        z = 0 * O[0]
        tm = np.asarray(0.5 * (A + B), np.float64)
        r = np.asarray(seg.r + z, np.float64)
        ends = [np.asarray(v + z, np.float64) for v in quad_ends(seg, q)]
    else:
        o, d, a, b = _segments(rng, bbox, SEGMENTS)
        seg, env = quad_env(NUMPY, list(o.T), list(d.T), a, b)
        (q,) = evaluate_quadratic([f], env, seg)
        tm, r = 0.5 * (a + b), np.broadcast_to(seg.r, a.shape)
        ends = [np.broadcast_to(v, a.shape) for v in quad_ends(seg, q)]
    for k, t in enumerate((tm - r, tm + r)):
        lo, hi = ends[2 * k], ends[2 * k + 1]
        assert_inside(f"end {k}", lo, hi, _values(f, o, d, t[:, None])[:, 0])
    assert np.isfinite(ends[0]).any()           # the check is not vacuous


def test02_exact_on_quadratics(rng):
    """Along a ray, x^2 + 2 y^2 - z^2 + x z - 0.3 and the distance to a point
    (sqrt of a quadratic, less a radius) are exact quadratic forms: their
    ranges are the analytic ones (the values at the ends and at the
    vertex), to a few units of rounding. Oracle: closed form in float64."""
    o, d, a, b = _segments(rng, ((-1, -1, -1), (1, 1, 1)), 500, scale=0.9)
    q = parse("x^2 + 2*y^2 - z^2 + x*z - 0.3")
    dist = parse("sqrt((x - 0.2)^2 + (y + 0.1)^2 + z^2) - 0.5")
    (qlo, qhi), (dlo, dhi) = _ranges([q, dist], o, d, a, b, "numpy64")
    # q(o + t d) = A t^2 + B t + C
    t3 = np.stack([a, 0.5 * (a + b), b], 1)
    vq = _values(q, o, d, t3)
    A = (vq[:, 0] - 2 * vq[:, 1] + vq[:, 2]) / (2 * (0.5 * (b - a)) ** 2)
    B = (vq[:, 2] - vq[:, 0]) / (b - a) - A * (a + b)
    tv = np.clip(-B / (2 * A), a, b)
    ends = np.stack([t3[:, 0], t3[:, 2], tv], 1)
    v = _values(q, o, d, ends)
    exact = (v.min(1), v.max(1))
    scale = np.abs(v).max(1) + 1
    assert np.all(qlo <= exact[0]) and np.all(qhi >= exact[1])
    assert np.all(exact[0] - qlo < 1e-12 * scale) and np.all(qhi - exact[1] < 1e-12 * scale)
    # the distance: closest approach to the centre, clipped to the segment
    c = np.array([0.2, -0.1, 0.0])
    tc = np.clip(((c - o) * d).sum(1), a, b)
    vd = _values(dist, o, d, np.stack([a, b, tc], 1))
    assert np.all(dlo <= vd.min(1)) and np.all(dhi >= vd.max(1))
    assert np.all(vd.min(1) - dlo < 1e-12) and np.all(dhi - vd.max(1) < 1e-12)


@pytest.mark.parametrize("name", ["tangle", "chmutov6", "torus"])
def test03_third_order_on_polynomials(name, rng):
    """On a degree-4 or -6 polynomial, the excess of the range over the
    sampled range shrinks as r^3: halving the segments divides the median
    excess by at least 6 (8 in the limit), while natural interval
    arithmetic's divides by about 2. Oracle: 2049 samples per segment."""
    from lgshape.surfaces import LIBRARY
    s = LIBRARY[name]()
    o, d, a, _ = _segments(rng, s.bbox, 300)
    excess = {}
    for w in (0.02, 0.01):
        b = a + w
        (lo, hi), = _ranges([s.expr], o, d, a, b, "numpy64")
        t = a[:, None] + w * np.linspace(0, 1, 2049)[None]
        v = _values(s.expr, o, d, t)
        nat = evaluate_interval(s.expr, segment_env(list(o.T), list(d.T), a, b, NUMPY), NUMPY)
        true = v.max(1) - v.min(1)
        excess[w] = (np.median((hi - lo) - true), np.median((nat.hi - nat.lo) - true))
    q_ratio = excess[0.02][0] / excess[0.01][0]
    n_ratio = excess[0.02][1] / excess[0.01][1]
    assert q_ratio > 6, (q_ratio, excess)
    assert n_ratio < 3, (n_ratio, excess)


def test04_unknowns_are_infinite():
    """A form that overflows or meets a NaN has an infinite range, never a
    narrow wrong one; an infinite interval parameter gives no information.
    Oracle: the definition (no finite interval encloses an unknown)."""
    m = NUMPY
    seg = Segment(m, np.array([0.5, 0.5, 0.5]))
    q = Quad(np.array([np.inf, np.nan, 1.0]), np.array([0.0, 1.0, np.inf]),
             np.array([0.0, 0.0, 0.0]), np.array([0.0, 0.0, 0.0]))
    r = quad_range(seg, q)
    assert np.all(r.lo == -np.inf) and np.all(r.hi == np.inf)
    x = coordinate(seg, np.zeros(3), np.ones(3), np.zeros(3))
    from lgshape.expr import node as N
    p = evaluate_quadratic(N.var("x") * N.var("p"), {"x": x, "p": Interval(np.full(3, -np.inf),
                                                                  np.full(3, 1.0))}, seg)
    r = quad_range(seg, p)
    assert np.all(r.lo == -np.inf) and np.all(r.hi == np.inf)


@pytest.mark.parametrize("k", [1e-30, 1e30])
def test05_scaled_near_tangent(k, rng):
    """k (x^2 + y^2 + z^2 - 1) on segments of rays passing 1e-4 inside or
    outside the unit sphere, in float32: the vertex term c1^2 / (4 c2)
    once underflowed for k = 1e-30 (a near-tangent root excluded). Oracle:
    sampled float64 values inside the range, no tolerance."""
    from lgshape.expr import node as N
    x, y, z = N.var("x"), N.var("y"), N.var("z")
    f = k * (x * x + y * y + z * z - 1.0)
    n = 1000
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    d = np.cross(nrm, rng.normal(size=(n, 3)))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = nrm * (1 + rng.choice([-1e-4, 1e-4], n))[:, None] - 0.5 * d
    a = 0.5 - 10 ** rng.uniform(-4, -1, n)
    b = 0.5 + 10 ** rng.uniform(-4, -1, n)
    o, d, a, b = (v.astype(np.float32).astype(np.float64) for v in (o, d, a, b))
    (lo, hi), = _ranges([f], o, d, a, b, "drjit32")
    t = a[:, None] + (b - a)[:, None] * np.linspace(0, 1, SAMPLES)[None]
    v = _values(f, o, d, t)
    assert np.all((lo[:, None] <= v) & (v <= hi[:, None]))
    assert np.all(np.isfinite(lo) & np.isfinite(hi))


@pytest.mark.parametrize("backend", ["numpy64", "drjit32"])
def test06_sdf_grazing_a_wall(backend, rng):
    """The capped cylinder SDF (radius 0.5, half height 0.6) on rays in the
    slab that close in on its side wall from 5 delta to delta (delta 1e-4
    to 1e-3): F = rho - r is in [delta, 5 delta] > 0, and the range's lower
    bound must be positive. The square of max(rho - r, 0), a constant form
    from sqrt's interval rule, once had a centred remainder reaching below
    0, so such rays bisected their whole segment down to the minimum width
    and hit the iteration cap (the stability suite's sdf_cylinder). Oracle:
    the closed form rho - r along the ray."""
    from lgshape.expr import node as N
    x, y, z = N.var("x"), N.var("y"), N.var("z")
    dx, dz = N.sqrt(x * x + y * y) - 0.5, N.abs_(z) - 0.6
    f = N.minimum(N.maximum(dx, dz), 0.0) + N.sqrt(N.maximum(dx, 0.0) ** 2 + N.maximum(dz, 0.0) ** 2)
    n = 400
    delta = 10 ** rng.uniform(-4, -3, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    u = np.stack([np.cos(phi), np.sin(phi), np.zeros(n)], 1)        # radial
    o = (0.5 + 5 * delta)[:, None] * u + np.array([0, 0, -0.5])
    d = -4 * delta[:, None] * u + np.array([0, 0, 1.0])             # to 0.5 + delta at t = 1
    a = rng.uniform(0, 0.5, n)
    b = a + rng.uniform(0.01, 0.5, n)
    if backend == "drjit32":
        o, d, a, b = (v.astype(np.float32).astype(np.float64) for v in (o, d, a, b))
    (lo, hi), = _ranges([f], o, d, a, b, backend)
    t = a[:, None] + (b - a)[:, None] * np.linspace(0, 1, SAMPLES)[None]
    v = _values(f, o, d, t)
    assert np.all((lo[:, None] <= v) & (v <= hi[:, None]))
    assert np.all(lo > 0), (np.sum(lo <= 0), lo[lo <= 0][:3])


def _clip(f, o, d, a, b, backend):
    """quad_clip over the segments o + [a, b] d: (free, first t, cross t,
    crossed, tm, r)."""
    if backend == "numpy64":
        seg, env = quad_env(NUMPY, list(o.T), list(d.T), a, b)
        (q,) = evaluate_quadratic([f], env, seg)
        free, s1, s2, crossed, _ = quad_clip(seg, q)
        tm, r = 0.5 * (a + b), np.broadcast_to(seg.r, a.shape)
        n = len(a)
        return (np.broadcast_to(free, n), tm + np.broadcast_to(s1, n), tm + np.broadcast_to(s2, n),
                np.broadcast_to(crossed, n), tm, r)
    m = DrJitMath(Float)
    O, D = [Float(o[:, i]) for i in range(3)], [Float(d[:, i]) for i in range(3)]
    A, B = Float(a), Float(b)
    seg, env = quad_env(m, O, D, A, B)
    (q,) = evaluate_quadratic([f], env, seg)
    free, s1, s2, crossed, _ = quad_clip(seg, q)
    z = 0 * O[0]
    tm = np.asarray(0.5 * (A + B), np.float64)
    return (np.asarray(free | (z > 0)), tm + np.asarray(s1 + z, np.float64),
            tm + np.asarray(s2 + z, np.float64), np.asarray(crossed | (z > 0)), tm,
            np.asarray(seg.r + z, np.float64))


@pytest.mark.parametrize("backend", ["numpy64", "drjit32"])
@pytest.mark.parametrize("case", ALL_CASES, ids=case_id)
def test07_clip_sound(case, backend, rng):
    """``quad_clip``: where it says a segment is free of roots, f keeps one
    strict sign on it; elsewhere f keeps one strict sign on [tm - r, first]
    (the part it cuts off), and where it says the enclosure has crossed, f
    at ``cross`` has the other sign (or is undefined). Oracle: float64
    values of f at 65 points of each part (ends included; NaN, an undefined
    point, is no root) and at ``cross``. No tolerance."""
    f, bbox = case_expr(*case)
    o, d, a, b = _segments(rng, bbox, SEGMENTS)
    if backend == "drjit32":
        o, d, a, b = (v.astype(np.float32).astype(np.float64) for v in (o, d, a, b))
    free, first, cross, crossed, tm, r = _clip(f, o, d, a, b, backend)
    end = np.where(free, tm + r, first)
    cut = free | (first > tm - r)
    u = np.linspace(0, 1, 65)[None, :]
    t = (tm - r)[:, None] + u * (end - (tm - r))[:, None]
    v = _values(f, o, d, t)
    with np.errstate(invalid="ignore"):
        pos, neg = (v > 0) | np.isnan(v), (v < 0) | np.isnan(v)
    one_sign = pos.all(1) | neg.all(1)
    assert one_sign[cut].all(), (f"{int((~one_sign & cut).sum())} cut parts hold a root or a "
                                 f"zero of f")
    vx = _values(f, o, d, cross[:, None])[:, 0]
    with np.errstate(invalid="ignore"):
        other = np.isnan(vx) | np.where(v[:, 0] > 0, vx < 0, vx > 0)
    assert other[crossed].all(), f"{int((~other & crossed).sum())} crossings without a sign change"


def test08_clip_finds_quadric_roots(rng):
    """On a quadric the form is exact: the first root the clip allows is the
    first root of f, to rounding. Oracle: the float64 roots of the quadratic
    in t (closed form from three values); segments holding a root."""
    f = parse("x^2 + 2*y^2 + 3*z^2 + x*y - y*z + 0.3*x - 0.8")
    o, d, a, b = (v.astype(np.float32).astype(np.float64)
                  for v in _segments(rng, ((-1.2,) * 3, (1.2,) * 3), SEGMENTS, scale=0.9))
    t3 = np.stack([a, 0.5 * (a + b), b], 1)
    v3 = _values(f, o, d, t3)
    h = 0.5 * (b - a)
    A = (v3[:, 0] - 2 * v3[:, 1] + v3[:, 2]) / (2 * h * h)
    B = (v3[:, 2] - v3[:, 0]) / (2 * h)
    C = v3[:, 1]                           # f(tm + s) = A s^2 + B s + C
    disc = B * B - 4 * A * C
    with np.errstate(invalid="ignore"):
        s = np.sort(np.stack([(-B - np.sqrt(disc)) / (2 * A), (-B + np.sqrt(disc)) / (2 * A)], 1), 1)
        s = np.where((s >= -h[:, None]) & (s <= h[:, None]), s, np.inf)
    root = 0.5 * (a + b) + s.min(1)
    has = np.isfinite(root) & (root > a + 1e-3 * (b - a))
    for backend in ("numpy64", "drjit32"):
        free, first, cross, crossed, _, _ = _clip(f, o, d, a, b, backend)
        assert not free[has].any()
        assert np.all(first[has] <= root[has])
        # the crossing: the first root lies in (first, cross]
        assert np.all(cross[has & crossed] >= root[has & crossed])
        assert np.mean(crossed[has]) > 0.9
        gap = (root - first)[has] / (b - a)[has]
        assert np.median(gap) < 1e-2 and np.mean(gap < 0.05) > 0.9, np.percentile(gap, [50, 90])
        assert free[~np.isfinite(s).any(1) & (disc < 0)].mean() > 0.9


def test09_clamped_kernel_across_its_clamp(rng):
    """A Wyvill blob's kernel k(min(u, 1)) (u = |p|^2) and g on short
    segments through the clamp sphere u = 1, where min's arguments cross.
    Oracle: float64 samples of f and g (65 a segment, ends included) inside
    the forms' ranges. Tightness: k has zero slope at the clamp, so g is
    small there; the derivative keeps k'(m) as one factor of the clamp's
    step (diff._factored), and min's form is the chord (quadratic._chord),
    so g's range shrinks with the segment (about 2 L wide; term by term,
    the step's [0, 1] times each term gave about 7.7e3 L at L = 1e-3) and
    f's is first order (about 1.4 L; the interval rule's constant form gave
    about 3 L)."""
    u = "(x^2 + y^2 + z^2)"
    f = parse(f"0.5 - (1 - 4/9*min({u}, 1)^3 + 17/9*min({u}, 1)^2 - 22/9*min({u}, 1))")
    g, _ = ray_derivatives(f)
    n, L = 4000, 1e-3
    p = rng.normal(size=(n, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    a = -L * rng.uniform(0.1, 0.9, n)
    b = a + L
    t = a[:, None] + L * np.linspace(0, 1, 65)[None]
    widths = {}
    for name, e, (lo, hi) in zip("fg", (f, g), _ranges([f, g], p, d, a, b, "numpy64")):
        v = _values(e, p, d, t)
        assert ((lo[:, None] <= v) & (v <= hi[:, None])).all(), name
        widths[name] = np.median(hi - lo) / L
    assert widths["g"] < 10, widths
    assert widths["f"] < 2, widths


@pytest.mark.parametrize("f", [
    "min(sqrt(x^2 + y^2 + z^2) - 0.6, max(max(abs(x) - 0.4, abs(y) - 0.9), abs(z) - 0.3))",
    "0.5 - (1 - min(x^2 + y^2 + z^2, 1))^2 - (1 - min((x - 0.5)^2 + y^2 + z^2, 1))^2",
    "abs(x * y - z) - 0.1",
])
def test12_mixed_cases_in_a_branch(f, rng, monkeypatch):
    """min, max and abs compute the form of a mixed case (neither side
    provably wins) in a Dr.Jit branch (``BRANCH_MIXED``): a packet with no
    mixed lane skips it. Oracle: the same forms computed without the branch
    (every case for every lane, then selected), which test01's sampled
    float64 values hold; each f has both kinds of lanes here."""
    from lgshape.expr import quadratic
    e = parse(f)
    o, d, a, b = _segments(rng, ((-1, -1, -1), (1, 1, 1)), 3000)
    out = {}
    for branch in (False, True):
        monkeypatch.setattr(quadratic, "BRANCH_MIXED", branch)
        m = DrJitMath(Float)
        O, D = [Float(o[:, i]) for i in range(3)], [Float(d[:, i]) for i in range(3)]
        seg, env = quad_env(m, O, D, Float(a), Float(b))
        (q,) = evaluate_quadratic([e], env, seg)
        out[branch] = [np.asarray(v + 0 * O[0], np.float64) for v in (q.c0, q.c1, q.c2, q.R)]
    for v0, v1 in zip(out[False], out[True]):
        assert np.array_equal(v0, v1, equal_nan=True)
    lo, hi = _ranges([e], o, d, a, b, "drjit32")[0]
    t = a[:, None] + (b - a)[:, None] * np.linspace(0, 1, SAMPLES)[None]
    v = _values(e, o, d, t)
    assert np.all((lo[:, None] <= v) & (v <= hi[:, None]))



@pytest.mark.parametrize("f", ["exp(-400 * ((x - 0.3)^2 + y^2 + z^2))",
                               "0.3 - exp(-400 * ((x - 0.3)^2 + y^2 + z^2))"
                               " - exp(-60 * (x^2 + (y + 0.4)^2))"])
def test13_negligible_exp(f, rng, monkeypatch):
    """exp of an argument whose form stays below EXP_FLOOR (-80) over a
    segment is the constant form [0, EXP_TINY] (``NEGLIGIBLE_EXP``, in a
    branch a packet skips), and its point value, where the argument with
    its error stays below EXP_FLOOR - 1, is 0 within EXP_TINY. Oracles:
    the forms and point values computed without it (every lane's exp), bit
    for bit on the other lanes (on LLVM: see below for CUDA); sampled
    float64 values of f inside the forms' ranges (test01's rule) and
    within the point values' error bounds of the float64 value. Narrow
    Gaussians: most segments of the box see them below the floor, some do
    not."""
    from lgshape.expr import ops
    from lgshape.expr.evaluate import evaluate_with_error
    e = parse(f)
    gauss = e if e.op == "exp" else e.args[0].args[1]       # exp(-400 ...)
    o, d, a, b = _segments(rng, ((-1, -1, -1), (1, 1, 1)), 3000)
    m, m64 = DrJitMath(Float), DrJitMath(JIT.Float64)
    O, D = [Float(o[:, i]) for i in range(3)], [Float(d[:, i]) for i in range(3)]
    tm = 0.5 * (a + b)
    P = {v: JIT.Float64(o[:, i] + tm * d[:, i]) for i, v in enumerate("xyz")}
    forms, points = {}, {}
    for flag in (False, True):
        monkeypatch.setattr(ops, "NEGLIGIBLE_EXP", flag)
        seg, env = quad_env(m, O, D, Float(a), Float(b))
        q, qa = evaluate_quadratic([e, gauss.args[0]], env, seg)
        forms[flag] = [np.asarray(v + 0 * O[0], np.float64) for v in (q.c0, q.c1, q.c2, q.R)]
        arg_hi = np.asarray(quad_range(seg, qa).hi + 0 * O[0], np.float64)
        (v, ev), (va, eva) = evaluate_with_error([e, gauss.args[0]], P, {}, m64)
        points[flag] = [np.asarray(x + 0 * P["x"], np.float64) for x in (v, ev)]
        arg_point = np.asarray(va + eva + 0 * P["x"], np.float64)
    low = arg_hi < ops.EXP_FLOOR
    assert low.mean() > 0.5 and (~low).any()               # both kinds of lanes
    if e is gauss:
        assert np.all(forms[True][0][low] == 0) and np.all(forms[True][1][low] == 0)
        assert np.all(forms[True][3][low] == np.float32(ops.EXP_TINY))
    bitwise = JIT.__name__ == "drjit.llvm"   # see the point values' check below
    if bitwise:
        for x, y in zip(forms[False], forms[True]):
            assert np.array_equal(x[~low], y[~low], equal_nan=True)
    t = a[:, None] + (b - a)[:, None] * np.linspace(0, 1, SAMPLES)[None]
    v = _values(e, o, d, t)
    for flag in (False, True):
        monkeypatch.setattr(ops, "NEGLIGIBLE_EXP", flag)
        lo, hi = _ranges([e], o, d, a, b, "drjit32")[0]
        assert np.all((lo[:, None] <= v) & (v <= hi[:, None])), flag
    # point values at the middles (the exact value is f at the float64 point)
    low_p = arg_point < ops.EXP_FLOOR - 1.0
    assert low_p.mean() > 0.5 and (~low_p).any()
    ref = _values(e, o, d, tm[:, None])[:, 0]
    for flag in (False, True):
        val, err = points[flag]
        assert np.all(np.abs(val - ref) <= err), flag
    if bitwise:
        # Not on CUDA: its PTX (mul/add without .rn) lets the assembler fuse a
        # product and a sum into an fma differently in the two kernels; on an
        # H200 the arguments (about -70) came out an ulp apart on 23 of 135
        # lanes, their exps 1.4e-14 apart (the forms' c0, R likewise, a
        # float32 ulp), all within the bounds checked above.
        assert np.array_equal(points[False][0][~low_p], points[True][0][~low_p])
        assert np.array_equal(points[False][1][~low_p], points[True][1][~low_p])
    if e is gauss:
        assert np.all(points[True][0][low_p] == 0)
