"""The ray search against float64 polynomial roots.

Oracle: for each algebraic library surface, F(t) along every ray is expanded
in float64 (from the formula written out below, independently of the
expression DAG and of the Dr.Jit kernel) and all its roots are taken from the
companion matrix (:func:`lgshape.reference.polynomial_roots`); the close
pairs of test03 come from closed forms (sphere) or from each factor's roots
(a slab between two level sets). Each verified first root is polished by
float64 bisection in its bracket. 100k rays per surface: from outside the
box, starting inside it, and grazing the surface near its silhouettes.

The rules (:func:`oracles.check_first_roots`, whose docstring defines the
classes): with tol = 1e-6 x the box diagonal / |d|, the documented
refinement tolerance, checked on ``RayResult.t64``:
- every ray whose first root in range is a verified real simple root (a
  float64 sign change across a bracket that holds no other root, at least
  2e-6 x diag wide) hits it, |t64 - r| <= tol; that includes close pairs (a
  second root within 2e-4 x diag), roots near the range ends and roots
  with a faint slope;
- simple roots with a float32 margin (isolated by 2e-4 x diag) are proven
  by the monotonicity test: ``unresolved`` is False;
- a ray without a root in range is a miss; no hit away from the first root;
- the one allowance is the near-tangent ray (first candidate a complex pair
  with |Im t| < 1e-4 x diag, a near-double root, a root at the range end):
  its hit may be at that touch (within tol + |Im t|) or at the next verified
  root, or it may miss if no verified root follows. The test bounds these
  rays at TANGENT_MAX = 1e-4 of the rays.
Measured class counts of test01 (100k rays each; simple / pair / end /
faint / none / tangent): barth_sextic 36451 / 2 / 9 / 12866 / 50672 / 0,
chmutov6 86928 / 0 / 23 / 200 / 12848 / 1, clebsch 64395 / 0 / 18 / 3549 /
32035 / 3, kummer 53659 / 1 / 28 / 8405 / 37907 / 0, tangle 67131 / 0 / 12 /
530 / 32326 / 1, torus 60658 / 0 / 6 / 1695 / 37641 / 0; test02's camera
rays: at most 2 tangent (barth_sextic) of 65536. So the allowance covers at
most 3e-5 of the rays (the previous rule, "a hit near any root", covered
every ray with a root outside its float32-margin simple class: 12.9% of
barth_sextic's rays, 13-26% of the hits on some surfaces).
Tangent touches (even multiplicity) may go either way: the kernel reports a
root only where F changes sign or is proven to touch 0 in float64.
"""
import math

import numpy as np
import pytest

import lgshape
import lgshape.evaluator
import lgshape.trace
from lgshape.reference import along, clip_to_box, polynomial_roots
from oracles import check_first_roots, sphere_roots
from conftest import JIT_AD

PHI = (1 + math.sqrt(5)) / 2
S2 = math.sqrt(2)
LAM = (3 * 1.69 - 1) / (3 - 1.69)


def T6(u):
    """Chebyshev T6(u) = 32 u^6 - 48 u^4 + 18 u^2 - 1 (Horner form in u^2)."""
    u2 = u * u
    return ((32 * u2 - 48) * u2 + 18) * u2 - 1


FORMULAS = {   # name: (degree, F(X, Y, Z) in float64)
    "torus": (4, lambda X, Y, Z: (X**2 + Y**2 + Z**2 + 1 - 0.16)**2 - 4 * (X**2 + Y**2)),
    "tangle": (4, lambda X, Y, Z: X**4 - 5 * X**2 + Y**4 - 5 * Y**2 + Z**4 - 5 * Z**2 + 11.8),
    "barth_sextic": (6, lambda X, Y, Z: 4 * (PHI**2 * X**2 - Y**2) * (PHI**2 * Y**2 - Z**2)
                     * (PHI**2 * Z**2 - X**2) - (1 + 2 * PHI) * (X**2 + Y**2 + Z**2 - 1)**2),
    "kummer": (4, lambda X, Y, Z: (X**2 + Y**2 + Z**2 - 1.69)**2 - LAM * (1 - Z - S2 * X)
               * (1 - Z + S2 * X) * (1 + Z + S2 * Y) * (1 + Z - S2 * Y)),
    "chmutov6": (6, lambda X, Y, Z: T6(X) + T6(Y) + T6(Z)),
    "clebsch": (3, lambda X, Y, Z: 81 * (X**3 + Y**3 + Z**3) - 189 * (X**2 * Y + X**2 * Z + Y**2 * X
                + Y**2 * Z + Z**2 * X + Z**2 * Y) + 54 * X * Y * Z + 126 * (X * Y + X * Z + Y * Z)
                - 9 * (X**2 + Y**2 + Z**2) - 9 * (X + Y + Z) + 1),
}
N_OUT, N_IN, N_GRAZE = 40_000, 30_000, 30_000
TANGENT_MAX = 1e-4          # near-tangent allowance, fraction of the rays (see above)


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _rays(rng, F, degree, lo, hi):
    c, half = 0.5 * (lo + hi), 0.5 * np.linalg.norm(hi - lo)
    # From outside: a sphere around the box, aimed at points inside it.
    o1 = c + 1.5 * half * _unit(rng.normal(size=(N_OUT, 3)))
    d1 = _unit(lo + (hi - lo) * rng.uniform(0, 1, (N_OUT, 3)) - o1)
    # Starting inside the box.
    o2 = lo + (hi - lo) * rng.uniform(0, 1, (N_IN, 3))
    d2 = _unit(rng.normal(size=(N_IN, 3)))
    # Grazing: through surface points, perpendicular to the normal, nudged off.
    t0, t1 = clip_to_box(o1, d1, lo, hi)
    roots = polynomial_roots(F, degree, o1, d1, t0, t1)
    real = np.where((np.abs(roots.imag) < 1e-9) & (roots.real >= t0[:, None]) & (roots.real <= t1[:, None]),
                    roots.real, np.inf)
    first = real.min(1)
    sel = np.flatnonzero(np.isfinite(first))[:N_GRAZE]
    sel = rng.choice(sel, N_GRAZE)
    p = o1[sel] + first[sel, None] * d1[sel]
    e = 1e-6
    grad = np.stack([(F(*(p + e * ax).T) - F(*(p - e * ax).T)) / (2 * e) for ax in np.eye(3)], 1)
    n = _unit(grad)
    d3 = _unit(np.cross(n, rng.normal(size=n.shape)))
    o3 = p - 2 * half * d3 + n * (2 * half * 1e-3) * rng.uniform(-1, 1, (N_GRAZE, 1))
    o = np.concatenate([o1, o2, o3]).astype(np.float32)
    d = np.concatenate([d1, d2, d3]).astype(np.float32)
    return o, d


@pytest.mark.parametrize("name", sorted(FORMULAS))
def test01_matches_polynomial_roots(name, rng):
    """100k rays (outside, inside, grazing) against the companion-matrix
    roots of the written-out formula, under the rules of the module
    docstring."""
    degree, F = FORMULAS[name]
    spec = lgshape.surfaces.LIBRARY[name]()
    lo, hi = np.asarray(spec.bbox[0]), np.asarray(spec.bbox[1])
    surf = lgshape.Surface(spec)
    assert surf.ray_polynomial            # (degree 3-6: each ray's polynomial)
    counts = _check(surf, F, degree, *_rays(rng, F, degree, lo, hi),
                    groups=np.repeat(["outside", "inside", "grazing"], [N_OUT, N_IN, N_GRAZE]))
    # The grazing rays exercise silhouettes: many simple first roots there;
    # and many rays have no root (misses are checked too).
    assert counts["by_group"]["grazing"]["simple"] > 5_000, counts
    assert counts["none"] > 10_000, counts


@pytest.mark.parametrize("name", ["barth_sextic", "chmutov6"])
def test01c_expression_path(name, rng):
    """The same polynomials with ``ray_polynomial`` off: each test evaluates
    the expression's quadratic forms (the path of every f that is not a
    polynomial of degree 3-8). 100k rays, test01's oracle and rules."""
    degree, F = FORMULAS[name]
    spec = lgshape.surfaces.LIBRARY[name]()
    lo, hi = np.asarray(spec.bbox[0]), np.asarray(spec.bbox[1])
    surf = lgshape.Surface(spec)
    surf.ray_polynomial = False
    o32, d32 = _rays(rng, F, degree, lo, hi)
    groups = np.repeat(["outside", "inside", "grazing"], [N_OUT, N_IN, N_GRAZE])
    res = surf.trace(o32, d32)
    counts = _check(surf, F, degree, o32, d32, groups=groups, res=res)
    assert counts["by_group"]["grazing"]["simple"] > 5_000, counts


@pytest.mark.parametrize("name", ["barth_sextic", "chmutov6"])
def test01d_point_left_out_where_the_forms_decide(name, rng, monkeypatch):
    """On the expression path, an interval whose quadratic forms decide it
    (F's range excludes 0; or g keeps one sign and F's signs at the ends
    are known, for an f defined everywhere) takes no point value of F
    (``FORM_DECIDES``). With and without that, on test01's rays: both
    answers hold under test01's oracle and rules (companion-matrix roots),
    the hits are the same rays, and the point values left out show in
    fewer evaluations."""
    degree, F = FORMULAS[name]
    spec = lgshape.surfaces.LIBRARY[name]()
    lo, hi = np.asarray(spec.bbox[0]), np.asarray(spec.bbox[1])
    o32, d32 = _rays(rng, F, degree, lo, hi)
    o32, d32 = o32[::4], d32[::4]
    res = {}
    for decides in (False, True):
        monkeypatch.setattr(lgshape.evaluator, "FORM_DECIDES", decides)
        surf = lgshape.Surface(spec)
        assert surf.total
        surf.ray_polynomial = False
        res[decides] = surf.trace(o32, d32)
        _check(surf, F, degree, o32, d32, None, min_simple=5_000, res=res[decides])
    assert np.array_equal(np.asarray(res[False].hit), np.asarray(res[True].hit))
    ev = {k: int(np.asarray(r.evals, np.int64).sum()) for k, r in res.items()}
    assert ev[True] < 0.9 * ev[False], ev


FORMULAS["sphere"] = (2, lambda X, Y, Z: X**2 + Y**2 + Z**2 - 1)

# Quadrics (degree 2): the search starts from the first root that F's exact
# quadratic form along the whole ray allows (``quad_clip``), not from a walk.
QUADRICS = {   # name: (f, F in float64, box half-size)
    "ellipsoid": ("x^2 + 2*y^2 + 3*z^2 + x*y - y*z + 0.3*x - 0.8",
                  lambda X, Y, Z: X**2 + 2 * Y**2 + 3 * Z**2 + X * Y - Y * Z + 0.3 * X - 0.8, 1.2),
    "hyperboloid1": ("x^2 + y^2 - z^2 - 0.25", lambda X, Y, Z: X**2 + Y**2 - Z**2 - 0.25, 1.0),
    "hyperboloid2": ("z^2 - x^2 - 0.5*y^2 - 0.1", lambda X, Y, Z: Z**2 - X**2 - 0.5 * Y**2 - 0.1,
                     1.0),
    "cylinder": ("(x - 0.1)^2 / 0.64 + y^2 - 0.5", lambda X, Y, Z: (X - 0.1)**2 / 0.64 + Y**2 - 0.5,
                 1.0),
    "paraboloid": ("x^2 + y^2 - z - 0.5", lambda X, Y, Z: X**2 + Y**2 - Z - 0.5, 1.0),
}


def _spec(name):
    """A library surface, or one of QUADRICS."""
    if name in QUADRICS:
        f, _, h = QUADRICS[name]
        return lgshape.surfaces.Implicit(name, lgshape.parse(f), ((-h,) * 3, (h,) * 3))
    return lgshape.surfaces.LIBRARY[name]()


@pytest.mark.parametrize("name", sorted(QUADRICS))
def test01b_quadrics_match_polynomial_roots(name, rng):
    """Quadrics, whose search starts from the first root F's quadratic form
    allows over the whole ray (no walk where it excludes a root): 100k rays
    (outside, inside, grazing) against float64 polynomial roots under the
    rules of the module docstring."""
    _, F, _ = QUADRICS[name]
    spec = _spec(name)
    surf = lgshape.Surface(spec)
    assert surf.quadric
    lo, hi = np.asarray(spec.bbox[0]), np.asarray(spec.bbox[1])
    counts = _check(surf, F, 2, *_rays(rng, F, 2, lo, hi), min_simple=20_000,
                    groups=np.repeat(["outside", "inside", "grazing"], [N_OUT, N_IN, N_GRAZE]))
    assert counts["none"] > 5_000, counts


@pytest.mark.parametrize("search,depth", [("interval", 7), ("taylor", 6), ("global", 6)])
@pytest.mark.parametrize("name", ["chmutov6", "barth_sextic", "sphere"])
def test02_camera_rays_every_mode(name, search, depth):
    """256^2 primary rays, each search mode (regressions: a root within one
    float32 step of a bisection point was skipped in the global mode; the
    refinement once returned a bracket midpoint on the sphere at depth 7).
    Oracle: the companion-matrix roots, under test01's rules."""
    from lgshape.camera import primary_rays
    degree, F = FORMULAS[name]
    spec = lgshape.surfaces.LIBRARY[name]()
    o32, d32 = primary_rays(spec.bbox, 256)
    _check(lgshape.Surface(spec, search=search, depth=depth), F, degree, o32, d32,
           groups=np.repeat(["camera"], len(o32)), min_simple=10_000)



@pytest.mark.parametrize("name", ["chmutov6", "tangle"])
def test02b_brick_map_walk(name, monkeypatch):
    """The walk through the brick map, which grids finer than
    DENSE_MAX_DEPTH use instead of the dense table (forced here at depth 6).
    Oracle: the companion-matrix roots, under test01's rules."""
    from lgshape import grid as G
    from lgshape.camera import primary_rays
    monkeypatch.setattr(G, "DENSE_MAX_DEPTH", 5)
    degree, F = FORMULAS[name]
    spec = lgshape.surfaces.LIBRARY[name]()
    surf = lgshape.Surface(spec, depth=6)
    assert not surf._kernel_data(_llvm_float()).grid.dense
    o32, d32 = primary_rays(spec.bbox, 192)
    _check(surf, F, degree, o32, d32, groups=np.repeat(["camera"], len(o32)),
           min_simple=5_000)


def _llvm_float():
    return JIT_AD.Float

def _check(surf, F, degree, o32, d32, groups, min_simple=30_000, tangent_max=TANGENT_MAX,
           roots=None, t_min=0.0, res=None):
    """The rules of the module docstring (:func:`oracles.check_first_roots`)
    with the companion-matrix roots of F (or ``roots``); at least
    ``min_simple`` simple first roots (the test exercises many), at most
    ``tangent_max`` x the rays in the near-tangent allowance (None: any);
    ``res``: the trace's result, where the caller has it. Returns the class
    counts."""
    if roots is None:
        o, d = o32.astype(np.float64), d32.astype(np.float64)
        t0, t1 = clip_to_box(o, d, surf.lo, surf.hi, t_min)
        roots = polynomial_roots(F, degree, o, d, t0, t1)
    counts = check_first_roots(surf, F, o32, d32, roots, groups=groups, t_min=t_min, res=res)
    assert counts["simple"] > min_simple, counts
    if tangent_max is not None:
        assert counts["tangent"] <= tangent_max * len(o32), counts
    return counts


# ---------------------------------------------------------------------------
# Close root pairs: the thin slivers the method exists for
# ---------------------------------------------------------------------------

def _graze(rng, F, degree, spec, n):
    """Rays tangent to the surface at random points of it (first roots of
    random rays), moved into the solid by up to 3e-7 (log-uniform): each
    passes through a sliver whose two roots are about sqrt(8 depth / k) apart
    (k the normal curvature); float32 rounding of o and d (~5e-8) spreads
    the depths further. The separations are measured by the oracle."""
    lo, hi = np.asarray(spec.bbox[0]), np.asarray(spec.bbox[1])
    c, half = 0.5 * (lo + hi), 0.5 * np.linalg.norm(hi - lo)
    o1 = c + 1.5 * half * _unit(rng.normal(size=(n, 3)))
    d1 = _unit(lo + (hi - lo) * rng.uniform(0, 1, (n, 3)) - o1)
    t0, t1 = clip_to_box(o1, d1, lo, hi)
    roots = polynomial_roots(F, degree, o1, d1, t0, t1)
    real = np.where((np.abs(roots.imag) < 1e-9) & (roots.real >= t0[:, None])
                    & (roots.real <= t1[:, None]), roots.real, np.inf)
    first = real.min(1)
    p = (o1 + first[:, None] * d1)[np.isfinite(first)]
    e = 1e-6
    grad = np.stack([(F(*(p + e * ax).T) - F(*(p - e * ax).T)) / (2 * e) for ax in np.eye(3)], 1)
    nrm = _unit(grad)
    d = _unit(np.cross(nrm, rng.normal(size=nrm.shape)))
    depth = 10 ** rng.uniform(-11, np.log10(3e-7), (len(p), 1))
    o = p - 0.3 * half * d - nrm * depth
    return o.astype(np.float32), d.astype(np.float32)


def _tangle_slab(c):
    """The slab c > T > 0 between two level sets of the tangle polynomial T:
    f = T (T - c), and the roots of each factor along rays (the oracle)."""
    from lgshape import parse
    T = FORMULAS["tangle"][1]
    text = "x^4 - 5*x^2 + y^4 - 5*y^2 + z^4 - 5*z^2 + 11.8"
    spec = lgshape.surfaces.Implicit("tangle_slab", parse(f"({text}) * ({text} - {c!r})"),
                                     lgshape.surfaces.tangle().bbox)

    def roots(o, d, t0, t1):
        return np.concatenate([polynomial_roots(T, 4, o, d, t0, t1),
                               polynomial_roots(lambda X, Y, Z: T(X, Y, Z) - c, 4, o, d, t0, t1)], 1)
    return spec, (lambda X, Y, Z: T(X, Y, Z) * (T(X, Y, Z) - c)), roots


#: case: (rays in the pool, bands of first-root separation (x diag) with the
#: least number of rays each must hold, about half the counts measured at
#: the seed: sphere 53 / 525 / 5699 / 7984, torus 134 / 1122 / 8144 / 4888,
#: slab 978 / 1994 / 23).
PAIR_CASES = {
    "sphere": (40_000, {(4e-6, 1e-5): 25, (1e-5, 3e-5): 250, (3e-5, 1e-4): 2500, (1e-4, 2e-4): 4000}),
    "torus": (40_000, {(4e-6, 1e-5): 60, (1e-5, 3e-5): 500, (3e-5, 1e-4): 4000, (1e-4, 2e-4): 2400}),
    "tangle_slab": (4_000, {(4e-6, 1e-5): 500, (1e-5, 1e-4): 1000, (1e-4, 2e-4): 10}),
}
SLAB = 1e-3          # the slab's level-set gap: first roots 4e-6..2e-4 x diag apart


@pytest.mark.parametrize("case", sorted(PAIR_CASES))
def test03_close_root_pairs(case, rng):
    """Rays whose first two roots are closer than 2e-4 x diag (down to 4e-6
    x diag, twice the kernel's minimum interval width): rays grazing the
    sphere (oracle: both roots in closed form) and the torus (companion
    matrix roots) through a thin sliver, and rays crossing the thin slab
    between the tangle's level sets T = 0 and T = 1e-3 (oracle: the roots of
    each factor). The FIRST root of every such ray must be found, at
    |t64 - r| <= 1e-6 x diag (same rules as test01; all of these rays are
    in the ``pair`` class: no allowance)."""
    n, bands = PAIR_CASES[case]
    if case == "tangle_slab":
        spec, F, roots_of = _tangle_slab(SLAB)
        lo, hi = np.asarray(spec.bbox[0]), np.asarray(spec.bbox[1])
        c, half = 0.5 * (lo + hi), 0.5 * np.linalg.norm(hi - lo)
        o = c + 1.5 * half * _unit(rng.normal(size=(n, 3)))
        d = _unit(lo + (hi - lo) * rng.uniform(0, 1, (n, 3)) - o)
        o32, d32 = o.astype(np.float32), d.astype(np.float32)
    else:
        degree, F = FORMULAS[case]
        spec = lgshape.surfaces.LIBRARY[case]()
        o32, d32 = _graze(rng, F, degree, spec, n)
        if case == "sphere":
            def roots_of(o, d, t0, t1):
                return sphere_roots(o, d, (0, 0, 0), 1.0)
        else:
            def roots_of(o, d, t0, t1):
                return polynomial_roots(F, degree, o, d, t0, t1)
    surf = lgshape.Surface(spec)
    diag = surf.diagonal
    o, d = o32.astype(np.float64), d32.astype(np.float64)
    t0, t1 = clip_to_box(o, d, surf.lo, surf.hi)
    roots = roots_of(o, d, t0, t1)
    real = np.where((roots.imag == 0) & (roots.real >= t0[:, None]) & (roots.real <= t1[:, None]),
                    roots.real, np.inf)
    real.sort(1)
    with np.errstate(invalid="ignore"):
        sep = (real[:, 1] - real[:, 0]) / diag
    keep = (sep >= 4e-6) & (sep < 2e-4)
    counts = {b: int(((sep >= b[0]) & (sep < b[1])).sum()) for b in bands}
    assert all(counts[b] >= m for b, m in bands.items()), f"too few close pairs: {counts}"
    o32, d32, roots = o32[keep], d32[keep], roots[keep]
    groups = np.where(sep[keep] < 1e-5, "4e-6..1e-5", np.where(sep[keep] < 1e-4, "1e-5..1e-4", "1e-4..2e-4"))
    cls = check_first_roots(surf, F, o32, d32, roots, groups=groups)
    assert cls["pair"] == len(o32), f"rays outside the pair class: {cls}"


@pytest.mark.parametrize("name", ["tangle", "barth_sextic", "chmutov6", "kummer", "clebsch",
                                  "ellipsoid", "hyperboloid1"])
def test04_occluded_matches_polynomial_roots(name, rng):
    """``occluded`` (an any-hit query, which stops at a bracket or at a
    sign change of F with g bounded) on 40k rays (outside, inside, grazing)
    with random t_max, and on shadow rays from points 1e-3 diagonals off
    the surface towards a light. Oracle: the companion-matrix roots in
    [t_min, t_max]: a ray with a verified root there (a sign change of F
    in float64 over +-h, h = 1e-4 diagonals or half the gap to a neighbour
    or an end, at least 2e-6) must be occluded; a ray with no root within
    1e-4 diagonals of the real axis there must not. Rays with only
    unverified roots (tangent touches, roots at an end) are left out, and
    counted."""
    degree, F = FORMULAS[name] if name in FORMULAS else (2, QUADRICS[name][1])
    spec = _spec(name)
    surf = lgshape.Surface(spec)
    lo, hi = np.asarray(spec.bbox[0]), np.asarray(spec.bbox[1])
    diag = float(np.linalg.norm(hi - lo))
    o32, d32 = _rays(rng, F, degree, lo, hi)
    o32, d32 = o32[::2], d32[::2]
    o, d = o32.astype(np.float64), d32.astype(np.float64)
    t0, t1 = clip_to_box(o, d, lo, hi)
    t_max = np.where(t1 > t0, t0 + (t1 - t0) * rng.uniform(0, 1.2, len(o)), 1.0)
    # shadow rays: first hits of the outside rays, moved off the surface
    # along the normal (to the ray's side), towards a light outside the box
    rts = polynomial_roots(F, degree, o, d, t0, t1)
    real = np.where((np.abs(rts.imag) < 1e-9) & (rts.real >= t0[:, None])
                    & (rts.real <= t1[:, None]), rts.real, np.inf).min(1)
    k = np.flatnonzero(np.isfinite(real))[:15_000]
    p = o[k] + real[k, None] * d[k]
    e = 1e-6
    n = _unit(np.stack([(F(*(p + e * ax).T) - F(*(p - e * ax).T)) / (2 * e)
                        for ax in np.eye(3)], 1))
    n = np.where((n * d[k]).sum(1, keepdims=True) > 0, -n, n)
    start = p + 1e-3 * diag * n
    light = 0.5 * (lo + hi) + np.array([0.6, 0.8, 1.0]) * diag
    dist = np.linalg.norm(light - start, axis=1)
    o32 = np.concatenate([o32, start.astype(np.float32)])
    d32 = np.concatenate([d32, _unit(light - start).astype(np.float32)])
    t_max = np.concatenate([t_max, dist]).astype(np.float32)
    occ = np.asarray(surf.occluded(o32, d32, t_max))

    o, d = o32.astype(np.float64), d32.astype(np.float64)
    t0, t1 = clip_to_box(o, d, lo, hi)
    t1 = np.minimum(t1, t_max.astype(np.float64))
    ok = t1 > t0
    rts = polynomial_roots(F, degree, o, d, np.where(ok, t0, 0), np.where(ok, t1, 1))
    delta, h_min = 1e-4 * diag, 2e-6 * diag
    with np.errstate(all="ignore"):
        near = ok[:, None] & (np.abs(rts.imag) < delta) & (rts.real >= t0[:, None] - delta) \
            & (rts.real <= t1[:, None] + delta)
        c = np.where(near, rts.real, np.nan)
        gap = np.full(c.shape, np.inf)
        for j in range(c.shape[1]):           # the gap to the nearest other candidate
            others = np.abs(c[:, [j]] - np.where(np.arange(c.shape[1]) == j, np.inf, c))
            gap[:, j] = np.nanmin(np.where(np.isnan(others), np.inf, others), 1)
        h = np.minimum.reduce([np.full(c.shape, delta), gap / 2, c - t0[:, None],
                               t1[:, None] - c])
        fm = along(F, o, d, np.where(near, c - h, 0))
        fp = along(F, o, d, np.where(near, c + h, 0))
        verified = near & (h >= h_min) & (np.sign(fm) * np.sign(fp) < 0)
    yes, no = verified.any(1), ~near.any(1)
    decided = yes | no
    assert np.array_equal(occ[yes], np.ones(int(yes.sum()), bool)), \
        f"{int((~occ[yes]).sum())} of {int(yes.sum())} rays with a root not occluded"
    assert not occ[no].any(), f"{int(occ[no].sum())} of {int(no.sum())} rays without a root occluded"
    assert yes.sum() > 5_000 and no.sum() > 5_000 and (~decided).mean() < 0.02, \
        (int(yes.sum()), int(no.sum()), int((~decided).sum()))


def _blobs_f(X, Y, Z):
    """The library blobs' f in float64, from its formula (threshold 0.5
    less three Wyvill kernels of radius 1, as written in
    :func:`lgshape.surfaces.blobs`), independent of the DAG."""
    total = 0.0
    for c in ((-0.45, 0.0, 0.0), (0.45, 0.0, 0.0), (0.0, 0.55, 0.2)):
        u = np.minimum((X - c[0])**2 + (Y - c[1])**2 + (Z - c[2])**2, 1.0)
        total = total + 1 - 4 / 9 * u**3 + 17 / 9 * u**2 - 22 / 9 * u
    return 0.5 - total


def _scanned_rays(bbox, F, rng):
    """96^2 camera rays and 4000 rays from inside the box, and their first
    roots from a float64 scan of F (4096 steps a ray, bisected; inf where
    none): (o32, d32, d as float64, ref)."""
    from lgshape.camera import primary_rays
    from lgshape.reference import first_sign_change
    lo, hi = np.asarray(bbox[0]), np.asarray(bbox[1])
    oc, dc = primary_rays(bbox, 96)
    oi = (lo + (hi - lo) * rng.uniform(0, 1, (4000, 3))).astype(np.float32)
    di = _unit(rng.normal(size=(4000, 3))).astype(np.float32)
    o32, d32 = np.concatenate([oc, oi]), np.concatenate([dc, di])
    o, d = o32.astype(np.float64), d32.astype(np.float64)
    t0, t1 = clip_to_box(o, d, lo, hi)
    return o32, d32, d, first_sign_change(F, o, d, t0, t1)


def test05_blobs_in_horner_form(rng, monkeypatch):
    """The expression path takes f's sums of powers in Horner form
    (``HORNER``; the blobs' cubic kernels): the first hits are the same as
    with f as written, and both are the first roots of a float64 scan of
    the formula (4096 steps a ray, bisected), within the refinement
    tolerance. 96^2 camera rays and 4000 rays from inside the box."""
    spec = lgshape.surfaces.LIBRARY["blobs"]()
    o32, d32, d, ref = _scanned_rays(spec.bbox, _blobs_f, rng)
    sizes = {}
    for h in (False, True):
        monkeypatch.setattr(lgshape.trace, "HORNER", h)
        surf = lgshape.Surface(spec)
        sizes[h] = surf.local_expr.size()
        res = surf.trace(o32, d32)
        hit, t64 = np.asarray(res.hit), np.asarray(res.t64)
        tol = 1e-6 * surf.diagonal / np.linalg.norm(d, axis=1)
        assert np.array_equal(hit, np.isfinite(ref)), (h, int((hit != np.isfinite(ref)).sum()))
        assert np.all(np.abs(t64[hit] - ref[hit]) <= tol[hit]), h
        assert not np.asarray(res.capped).any()
    assert sizes[True] < sizes[False]


GAUSS_CENTRES = ((-0.5, 0.0, 0.0), (0.5, 0.0, 0.1), (0.0, 0.5, 0.3), (0.1, -0.5, -0.3))


def _gauss_f(X, Y, Z):
    """Blinn's blobby molecules in float64, from the formula: 0.05 less four
    Gaussians exp(-200 |p - c|^2)."""
    total = 0.0
    for c in GAUSS_CENTRES:
        total = total + np.exp(-200 * ((X - c[0])**2 + (Y - c[1])**2 + (Z - c[2])**2))
    return 0.05 - total


def test06_gaussians_negligible_far_away(rng, monkeypatch):
    """A sum of narrow Gaussians (Blinn's blobs), searched with and without
    ``NEGLIGIBLE_EXP`` (an exp whose argument stays below -80 over an
    interval taken as [0, 1.81e-35]): the same first hits, and both the
    first roots of a float64 scan of the formula (4096 steps a ray,
    bisected) within the refinement tolerance. 96^2 camera rays and 4000
    rays from inside the box."""
    from lgshape.expr import ops
    text = "0.05 - " + " - ".join(
        f"exp(-200 * ((x - {c[0]})^2 + (y - {c[1]})^2 + (z - {c[2]})^2))" for c in GAUSS_CENTRES)
    bbox = ((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
    o32, d32, d, ref = _scanned_rays(bbox, _gauss_f, rng)
    assert 0.02 < np.isfinite(ref).mean() < 0.5
    for flag in (False, True):
        monkeypatch.setattr(ops, "NEGLIGIBLE_EXP", flag)
        surf = lgshape.Surface(text, bbox)
        res = surf.trace(o32, d32)
        hit, t64 = np.asarray(res.hit), np.asarray(res.t64)
        tol = 1e-6 * surf.diagonal / np.linalg.norm(d, axis=1)
        assert np.array_equal(hit, np.isfinite(ref)), (flag, int((hit != np.isfinite(ref)).sum()))
        assert np.all(np.abs(t64[hit] - ref[hit]) <= tol[hit]), flag
        assert not np.asarray(res.capped).any() and not np.asarray(res.unresolved).any()
