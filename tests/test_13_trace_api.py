"""The query API: intersect, occluded, normal, ranges, modes, inputs,
recompiles, frozen queries.

Oracles: float64 polynomial roots along each ray (torus, degree 4) for the
ranges and the search modes; central differences for normals; Dr.Jit's
kernel history for recompiles."""
import math

import numpy as np
import pytest

import drjit as dr
from conftest import JIT_AD

Array3f, Float = JIT_AD.Array3f, JIT_AD.Float

import lgshape
import lgshape.primitives
from lgshape.camera import primary_rays
from lgshape.reference import clip_to_box, polynomial_roots

TORUS = lambda X, Y, Z: (X**2 + Y**2 + Z**2 + 1 - 0.16)**2 - 4 * (X**2 + Y**2)  # noqa: E731


@pytest.fixture(scope="module")
def torus():
    return lgshape.Surface(lgshape.surfaces.torus())


def _rays(rng, n=3000):
    spec = lgshape.surfaces.torus()
    lo, hi = np.asarray(spec.bbox[0]), np.asarray(spec.bbox[1])
    o = (lo + hi) / 2 + 3.0 * rng.normal(size=(n, 3)) / 1.7
    d = lo + (hi - lo) * rng.uniform(0, 1, (n, 3)) - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return o.astype(np.float32), d.astype(np.float32), lo, hi


def _real_roots(o, d, lo, hi):
    o, d = o.astype(np.float64), d.astype(np.float64)
    t0, t1 = clip_to_box(o, d, lo, hi, t_min=-np.inf)
    r = polynomial_roots(TORUS, 4, o, d, t0, t1)
    return np.sort(np.where(np.abs(r.imag) < 1e-9, r.real, np.inf), 1)


def test01_ranges_find_the_next_roots(torus, rng):
    """t_min just past the first root gives the second; t_max before the
    first gives a miss."""
    o, d, lo, hi = _rays(rng)
    roots = _real_roots(o, d, lo, hi)
    first = np.where(roots > 0, roots, np.inf).min(1)
    t, hit = (np.asarray(v) for v in torus.intersect(o, d))
    ok = np.isfinite(first)
    assert np.allclose(t[ok], first[ok], atol=1e-4 * torus.diagonal)
    assert not hit[~ok].any() and np.all(np.isinf(t[~ok]))
    # second root, isolated from the first by 1e-3
    r2 = np.where(roots > first[:, None] + 1e-3, roots, np.inf).min(1)
    sel = ok & np.isfinite(r2)
    t2, hit2 = (np.asarray(v) for v in torus.intersect(o[sel], d[sel], t_min=Float(first[sel] + 5e-4)))
    assert hit2.all() and np.allclose(t2, r2[sel], atol=1e-4 * torus.diagonal)
    t3, hit3 = torus.intersect(o[ok], d[ok], t_max=Float(first[ok] - 1e-3))
    assert not np.asarray(hit3).any()


def test02_occluded_agrees_with_intersect(torus, rng):
    o, d, _, _ = _rays(rng)
    t, hit = (np.asarray(v) for v in torus.intersect(o, d))
    t_max = rng.uniform(0.5, 6.0, len(o))
    occ = np.asarray(torus.occluded(o, d, Float(t_max)))
    clear = np.abs(t - t_max) > 1e-3      # away from the boundary case
    assert np.array_equal(occ[clear], (hit & (t < t_max))[clear])


def test03_normals(torus, rng):
    o, d, _, _ = _rays(rng)
    t, hit = (np.asarray(v) for v in torus.intersect(o, d))
    p = (o + t[:, None] * d)[hit].astype(np.float64)
    n = np.asarray(torus.normal(p.astype(np.float32))).T
    e = 1e-6
    fd = np.stack([(TORUS(*(p + e * a).T) - TORUS(*(p - e * a).T)) / (2 * e) for a in np.eye(3)], 1)
    fd /= np.linalg.norm(fd, axis=1, keepdims=True)
    assert np.all(np.einsum("ij,ij->i", n, fd) > 1 - 1e-5)
    outside = TORUS(*o[hit].astype(np.float64).T) > 0
    assert np.all(np.einsum("ij,ij->i", n, d[hit])[outside] < 0)   # entering from outside
    assert np.all(np.einsum("ij,ij->i", n, d[hit])[~outside] > 0)  # leaving from inside


@pytest.mark.parametrize("search", ["taylor", "global"])
def test04_other_search_modes_match_roots(search, rng):
    """The seed's tests (local and global G) find the same nearest roots."""
    surf = lgshape.Surface(lgshape.surfaces.torus(), search=search)
    o, d, lo, hi = _rays(rng, 2000)
    roots = _real_roots(o, d, lo, hi)
    first = np.where(roots > 0, roots, np.inf).min(1)
    r = surf.trace(o, d)
    t = np.asarray(r.t)
    assert not np.asarray(r.capped).any()
    ok = np.isfinite(first)
    assert np.allclose(t[ok], first[ok], atol=1e-4 * surf.diagonal)
    assert np.all(np.isinf(t[~ok]))


def test05_hand_given_constants(rng):
    """The seed's mode: hand-given L (global pruning) and G; a G that is too
    small is the user's responsibility, a valid one gives the same roots."""
    spec = lgshape.surfaces.torus()
    auto = lgshape.Surface(spec)
    L = float(lgshape.bounds.lipschitz(spec.expr, auto.lo[None], auto.hi[None])[0])
    hand = lgshape.Surface(spec, L=L, G=auto.global_G())
    assert hand.search == "global"
    o, d, _, _ = _rays(rng, 1000)
    assert np.allclose(np.asarray(hand.intersect(o, d)[0]), np.asarray(auto.intersect(o, d)[0]),
                       atol=1e-4 * auto.diagonal, equal_nan=True)
    with pytest.raises(ValueError, match="L must be"):
        lgshape.Surface(spec, L=-1.0)


def test06_inputs_and_outputs():
    surf = lgshape.Surface("x^2 + y^2 + z^2 - 1", bbox=((-1.5,) * 3, (1.5,) * 3))
    o_np = np.array([[0, 0, -3], [0, 3, 3]], np.float32)
    d_np = np.array([[0, 0, 1], [1, 0, 0]], np.float32)
    t_np, hit_np = surf.intersect(o_np, d_np)
    t_dr, hit_dr = surf.intersect(Array3f(o_np.T), Array3f(d_np.T))
    assert np.array_equal(np.asarray(t_np), np.asarray(t_dr))
    assert np.asarray(t_np)[0] == pytest.approx(2.0, abs=1e-5)
    assert math.isinf(np.asarray(t_np)[1]) and not np.asarray(hit_np)[1]
    with pytest.raises(ValueError, match="bbox"):
        lgshape.Surface("x + y")
    with pytest.raises(lgshape.ParseError, match="position"):
        lgshape.Surface("x + * y", bbox=((0,) * 3, (1,) * 3))
    with pytest.raises(ValueError, match="search mode"):
        lgshape.Surface(lgshape.surfaces.sphere(), search="fast")


def test07_no_recompile_for_new_values():
    """Calling a Surface twice, or another Surface of the same expression
    shape with other constants, reuses the compiled kernel."""
    o, d = primary_rays(lgshape.surfaces.tangle().bbox, 32)
    o, d = Array3f(o.T), Array3f(d.T)
    dr.eval(o, d)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    hashes = []
    try:
        for c in (11.8, 11.8, 10.5):
            surf = lgshape.Surface(lgshape.surfaces.tangle(c))
            dr.kernel_history()
            r = surf.trace(o, d)
            dr.eval(r.t, r.hit, r.evals, r.capped)
            dr.sync_thread()
            hashes.append([k["hash"] for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT])
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert hashes[0] == hashes[1] == hashes[2]


def _fields(r):
    return [np.asarray(v) for v in (r.t64, r.hit, r.evals, r.iterations, r.capped, r.unresolved)]


@pytest.mark.parametrize("form", ["torus", "union"])
def test08_frozen_queries_match_traced_ones(form, rng):
    """A standalone query runs as a frozen function: its replays (other rays,
    other ray counts, t_max arrays, any-hit) give exactly what tracing the
    search anew gives (``freeze = False``), and a repeated call replays
    instead of recording again. Oracle: the traced search (checked against
    float64 polynomial roots here for the torus, and in test_11)."""
    if form == "torus":
        surf = lgshape.Surface(lgshape.surfaces.torus())
    else:
        c = rng.uniform(-1, 1, (60, 3))
        r = rng.uniform(0.1, 0.25, 60)
        surf = lgshape.Surface(lgshape.primitives.union(lgshape.primitives.spheres(c, r)),
                               ((-1.5,) * 3, (1.5,) * 3))
    counts = []
    for n in (1500, 700, 1500, 700, 1500, 1500, 1500):
        o_np, d_np, lo, hi = _rays(rng, n)
        # arrays of Dr.Jit's own memory (a mapped numpy buffer's alignment,
        # which varies, is part of a recording's layout)
        o, d = dr.copy(Array3f(o_np.T)), dr.copy(Array3f(d_np.T))
        t_max = dr.copy(Float(rng.uniform(0.5, 6.0, n).astype(np.float32)))
        dr.eval(o, d, t_max)
        res = {}
        for frozen in (True, False):
            surf.freeze = frozen
            res[frozen] = [_fields(surf.trace(o, d)), _fields(surf.trace(o, d, 0.01, 5.0)),
                           _fields(surf.trace(o, d, t_max=t_max, any_hit=True))]
        for a, b in zip(res[True], res[False]):
            for x, y in zip(a, b):
                assert np.array_equal(x, y, equal_nan=True)
        if form == "torus":
            roots = _real_roots(o_np, d_np, lo, hi)
            first = np.where(roots > 0, roots, np.inf).min(1)
            ok = np.isfinite(first)
            t64, hit = res[True][0][:2]
            assert hit[ok].all() and not hit[~ok].any()
            assert np.allclose(t64[ok], first[ok], atol=1e-4 * surf.diagonal)
        surf.freeze = True
        counts.append([surf._frozen[k, surf.ray_polynomial].n_recordings for k in (False, True)])
    # a layout may be recorded again on its first calls (its first recording
    # made the opaque constants of f, inputs from then on; Dr.Jit's own
    # checks, whose reasons it does not report, rarely record once more),
    # then it replays: of the last two rounds' 6 calls, at most one per
    # query kind recorded
    assert all(counts[-1][k] - counts[-3][k] <= 1 for k in (0, 1)), counts
    assert min(counts[0]) >= 1           # the queries did run frozen



def test09_numpy_rays_follow_the_variant():
    """numpy rays go to the backend of Mitsuba's variant (the suite's, LLVM
    or CUDA), and numpy beside a Dr.Jit array takes that array's type.
    Oracle: the sphere's analytic distance, 2 - 1 = 1."""
    import mitsuba as mi
    from conftest import VARIANT
    mi.set_variant(VARIANT)
    surf = lgshape.Surface(lgshape.surfaces.LIBRARY["sphere"]())
    o, d = np.array([[0.0, 0.0, -2.0]]), np.array([[0.0, 0.0, 1.0]])
    assert lgshape.trace.default_array3f() is JIT_AD.Array3f
    for rays in ((o, d), (Array3f(o.T), d), (o, Array3f(d.T))):
        res = surf.trace(*rays)
        assert type(res.t) is Float and math.isclose(res.t[0], 1.0, rel_tol=1e-6)


@pytest.mark.parametrize("f, total", [
    ("x^4 - 5*x^2 + y^4 - 5*y^2 + z^4 - 5*z^2 + 11.8", True),
    ("min(x^2 + y^2, 1) - 0.3 + exp(-abs(z)) * sin(x) * cos(y)", True),
    ("(x^2 + y^2 + z^2) / 2 - max(x, y)", True),
    ("sqrt(x^2 + y^2 + z^2) - 1", False),
    ("log(x^2 + 1) - 0.1", False),
    ("x / (y^2 + 1) - 0.1", False),
    ("x^-2 - 4", False),
])
def test10_total_expressions(f, total):
    """``Surface.total`` (f defined at every point, so its interval forms
    alone may prove the Kalra-Barr tests, see lgshape.evaluator.Evaluator._decided):
    True only for f built of ops defined on all reals (a division only by
    a constant, powers >= 0). Oracle: each expression's ops, by hand."""
    surf = lgshape.Surface(lgshape.parse(f), ((-1.5,) * 3, (1.5,) * 3))
    assert surf.total is total
