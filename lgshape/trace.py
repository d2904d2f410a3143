"""The guaranteed ray search (Kalra & Barr 1989) over the pruning grid.

For each ray, F(t) = f(o + t d), g = dF/dt, h = d^2F/dt^2 (exact symbolic
derivatives). The ray is clipped to the bounding box; a DDA visits the
occupied cells of the pruning grid nearest first (:mod:`lgshape.grid`); in
each cell the segment [a, b] is searched by stackless bisection (an implicit
binary tree: level and index). On an interval with midpoint t_m and half
width r, from an enclosure of F(t_m) (and g(t_m)) and bounds on the interval:

- *exclusion*: the enclosure of F over the interval has one sign -> no root;
- *monotonicity*: g keeps one sign on the interval -> at most one root; the
  signs of F at the ends decide whether it has one, and in which half;
- otherwise split.

The bounds come from one of :data:`SEARCH_MODES`: ``"interval"`` bounds F
and g over the interval by quadratic forms along the ray
(:mod:`lgshape.expr.quadratic`: exact on square sums, third order on
polynomials), and F also by the mean-value form F(t_m) + [g] [-r, r];
``"taylor"`` and ``"global"`` are the seed's test |g(t_m)| > G r with G >= |h|
local to the interval or global (plus F in F(t_m) +- |g(t_m)| r + [h] r^2/2).

**The contract for the roots of any f.** Where f is NaN or infinite there
is no surface. A root is reported only where F is continuous and crosses
zero, or is proven to touch it (|F| within its rounding error bound of 0):

- a sign change across a pole (where the interval of F over the smallest
  interval is unbounded) is not a root;
- a sign change across a gap where f is undefined is not a root (the
  derivative is unbounded at the edge of a domain, so the monotonicity test
  never spans the gap, and the ends must both be defined); where one end of
  a smallest interval is undefined, a root between the domain's edge and
  the defined end is looked for by bisecting towards the edge (``EDGE``);
- an f that is NaN or infinite at every sampled point of its box is refused
  at construction (:class:`Surface`).

**Point values** of F and g are evaluated in float64 with a running error
bound per value (:mod:`lgshape.pointerror`): the bound is relative to the
magnitudes actually evaluated along that ray, never a fixed absolute floor,
so the hits of k * f are those of f for any k that float32 intervals hold.
Signs are decided only outside that bound, so rounding noise never decides
one. Where the interval forms alone decide an interval (F's range excludes
0; or, for an f defined everywhere, g keeps one sign and F's signs at the
ends are known), no point value is taken. **Interval values** of F and g
over a ray interval are the ranges of float32 quadratic forms along the ray
(:mod:`lgshape.expr.quadratic`, which fall back on the interval rules of
:mod:`lgshape.interval` for the ops that are not polynomial); F over an
interval is the intersection of that range and the mean-value form where
those are finite, else (where F(t_m) is undefined or its derivative
unbounded: domain edges, poles) the natural interval form.

**Coordinates.** Each ray is moved to its box entry in float64, and f is
evaluated in coordinates local to the box centre (:mod:`lgshape.expr.shift`),
so geometry far from the origin is solved to the same relative accuracy as
near it. The returned t is float32 (as Mitsuba's), so it carries its own
rounding, ulp(t) / 2; :attr:`RayResult.t64` keeps the float64 value.

A bracketed single root is refined by safeguarded Newton in float64
(bisection where a step leaves the bracket) until the step, or the proven
distance |F| / min |g|, is below 1e-6 of the box diagonal. Intervals are
visited left to right, so the first root found is the nearest. Below a
minimum width (1e-6 of the diagonal) an interval that cannot be excluded is a
root where F changes sign across it (and is bounded there), or where F at its
middle is within its error bound of 0 (a tangent touch or singular point,
counted as ``unresolved``); otherwise the search goes on after it. Tangent
touches (roots of even multiplicity) may therefore be reported or not.

**Every ray ends.** Rays with a zero, infinite or NaN direction, or a NaN
origin, are misses. The grid walk is bounded by the number of cells a line
can cross; the search by ``max_iterations``. A ray that reaches the bound is
counted in ``capped`` and reported as a miss of the search, never silently:
the benchmark counts capped rays as defects.

Everything is Dr.Jit code without host round trips: it runs in LLVM and CUDA
and inside Mitsuba integrators. Constants are opaque, so another Surface of
the same expression shape reuses the compiled kernels.
"""
from __future__ import annotations

import math
import numbers
import sys
from dataclasses import dataclass, fields

import numpy as np

from . import bounds, grid as gridmod
from . import interval as iv
from .expr import raypoly, raytrig
from .expr.quadratic import (Segment, evaluate_quadratic, quad_clip, quad_ends, quad_env,
                             quad_range)
from .arraymath import NUMPY, DrJitMath, exact_arithmetic
from .expr import (Expr, evaluate, evaluate_with_error, gradient, hessian, parse,
                   ray_derivatives)
from .expr.horner import horner
from .expr.shift import localize
from .surfaces import Implicit
from . import tables as tablemod
from .tables import DeviceTables, TableForm, evaluate_points, find_tables

MAX_LEVEL = 22          # bisection depth bound inside one cell segment

#: How an interval of the ray is bounded: ``"interval"`` (g = dF/dt over the
#: interval by interval arithmetic, the mean-value form), ``"taylor"`` (the
#: seed's test with a local G >= |d^T H d| per interval) and ``"global"`` (the
#: seed's test with one G: hand-given, or the Hessian norm over the box).
SEARCH_MODES = ("interval", "taylor", "global")

#: Points sampled to check hand-given L and G, and that f is defined somewhere.
CHECK_SAMPLES = 4096

#: The expression path takes f with its sums of powers of a common
#: subexpression in Horner form (:mod:`lgshape.expr.horner`). Measured
#: against f as written (one process, interleaved, same hits), the blobs
#: (Wyvill's cubic kernels): camera / incoherent / shadow rays 1.09-1.11x /
#: 1.19-1.25x / 1.14-1.19x (two runs).
HORNER = True

#: Recordings kept per frozen query (one per ray count and argument layout;
#: least recently used dropped), see :meth:`Surface.trace`.
FREEZE_LIMIT = 8


@dataclass
class RayResult:
    """Per-ray output of :meth:`Surface.trace` (Dr.Jit arrays)."""
    t: object            # Float: nearest root, inf where none
    hit: object          # Bool
    evals: object        # UInt32: point + interval evaluations
    iterations: object   # UInt32: search + refinement iterations
    capped: object       # Bool: reached the iteration bound
    unresolved: object   # Bool: hit decided at the minimum width (tangent/singular)
    t64: object = None   # Float64: the same t before rounding to float32


def _as_expr(expr):
    if isinstance(expr, Implicit):
        return expr.expr, expr.bbox
    if isinstance(expr, TableForm):
        return expr, getattr(expr, "bbox", None)
    if isinstance(expr, str):
        return parse(expr), None
    if isinstance(expr, Expr):
        return expr, None
    raise TypeError(f"expected an expression, a string or a library surface, "
                    f"not {type(expr).__name__}")


#: The ops defined and finite on every finite argument (exp may overflow,
#: which its interval form shows as an infinite bound).
_TOTAL_OPS = frozenset(("add", "sub", "mul", "neg", "exp", "sin", "cos", "abs", "min", "max",
                        "step", "kink", "var", "const", "named"))


def _total(f: Expr) -> bool:
    """Whether f is defined at every point (see :attr:`Surface.total`):
    built from :data:`_TOTAL_OPS`, powers >= 0 and divisions by constants."""
    from .expr.node import topological
    for n in topological([f]):
        if n.op in _TOTAL_OPS or (n.op == "pow" and n.param >= 0):
            continue
        if n.op == "div" and n.args[1].op == "const" and n.args[1].param != 0:
            continue
        return False
    return True


def _check_box(bbox):
    try:
        lo, hi = (np.asarray(v, dtype=np.float64).reshape(3) for v in bbox)
    except (TypeError, ValueError):
        raise ValueError(f"bbox must be ((x0, y0, z0), (x1, y1, z1)), got {bbox!r}") from None
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise ValueError(f"bbox must be finite on every side, got {bbox}")
    if not np.all(hi > lo):
        raise ValueError(f"bbox must have min < max on every axis, got {bbox}")
    return lo, hi


def _check_int(name, v, lo, hi):
    if isinstance(v, bool) or not isinstance(v, numbers.Integral):
        raise ValueError(f"{name} must be an integer, got {v!r}")
    if not lo <= int(v) <= hi:
        raise ValueError(f"{name} must be between {lo} and {hi}, got {v}")
    return int(v)


#: The pruning depth of a plain expression of at most DEEP_MAX_NODES nodes
#: (6 for larger ones, whose build at depth 7 would take seconds and
#: gigabytes: the whole union of 100 spheres took 28 s and 5 GB). Measured
#: with the dense walk (512^2 camera rays, 2 cores): against depth 6, 14-25%
#: faster on tangle, the Barth sextic, Kummer, chmutov6, Clebsch, blobs,
#: spikes; the same on the torus and gyroid; 4% slower on the sphere. Its
#: build takes 0.05-2 s (chmutov6 the longest).
DEFAULT_DEPTH = 7
DEEP_MAX_NODES = 128


def _default_depth(tables, f=None) -> int:
    """:data:`DEFAULT_DEPTH` for a plain expression f of at most
    :data:`DEEP_MAX_NODES` nodes, else 6; for a table form, 6 and finer
    with more rows (7 from 300 rows, 8 from 3000), which keeps about one row
    per cell where primitives are dense (measured in the benchmark's scale
    section)."""
    if tables is not None:
        return 6 + (tables.rows >= 300) + (tables.rows >= 3000)
    return DEFAULT_DEPTH if f is None or f.size() <= DEEP_MAX_NODES else 6


#: A box whose longest edge is more than this many times its shortest is
#: pruned in the cube about it (:func:`_grid_box`).
FLAT_BOX = 2.0


def _grid_box(lo, hi):
    """The pruning grid's box for a plain expression: [lo, hi] itself, or,
    where its cells would be flat (longest edge over FLAT_BOX times the
    shortest), the cube about it (same centre, its longest edge), so that
    the cells are cubes. The walk's empty boxes are counted in cells, and a
    ray crosses a flat cell's short edge in a short step: in the torus's box
    (3.08 x 3.08 x 0.96) the cells were 3.2 times thinner in z, and its rays
    1.4-1.5x slower. Near-cubic boxes keep their cells: there the longer
    spans of cubic cells cost the search more than the walk gains (the
    blobs' box, 2.9 x 2.55 x 2.2, was 4-8% slower as a cube). Rays are
    clipped to [lo, hi] all the same; cells outside it are never walked."""
    ext = hi - lo
    if float(np.max(ext)) <= FLAT_BOX * float(np.min(ext)):
        return lo, hi
    side = float(np.max(ext))
    c = 0.5 * (lo + hi)
    return c - 0.5 * side, c + 0.5 * side


def _sample_points(lo, hi, n=CHECK_SAMPLES, seed=0):
    """Points of the box for the construction checks: a regular grid
    (corners and centres included) and random points."""
    k = 9
    axes = [np.linspace(lo[i], hi[i], k) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    rnd = lo + (hi - lo) * np.random.default_rng(seed).uniform(0, 1, (n - len(grid), 3))
    return np.concatenate([grid, rnd])


class Surface:
    """An implicit surface f = 0 inside a box, ready for guaranteed ray queries.

    ``expr``: an expression, a string of the expression language or a library
    surface (:mod:`lgshape.surfaces`, which brings its own box). ``bbox``:
    ``((x0, y0, z0), (x1, y1, z1))``, finite. ``L``: a hand-given Lipschitz
    constant of f over the box (then the pruning uses the seed's global test).
    ``G``: a hand-given bound of |d^2 F/dt^2| for unit directions (then the
    search uses it instead of local interval bounds). Hand-given L and G are
    checked against |grad f| and the Hessian's norm at sampled points and
    refused, naming the point, where they are too small. ``depth``: the
    pruning depth, an integer from 2 to 10 (2**depth cells per axis; default
    :data:`DEFAULT_DEPTH` = 7, 6 for expressions of over 128 nodes; for
    tables 6 to 8, see :func:`_default_depth`).
    ``search``: how ray intervals are bounded, see :data:`SEARCH_MODES`
    (default ``"interval"``, or ``"global"`` when ``G`` is given).
    ``max_iterations``: the per-ray bound on search steps.

    An f that is NaN or infinite at every sampled point of the box has no
    surface anywhere: that is refused with a ValueError.

    **Tables.** ``expr`` may be a :class:`~lgshape.tables.TableForm` (from
    :mod:`lgshape.primitives`), and a plain expression holding an n-ary min,
    max or sum of at least :data:`~lgshape.tables.MIN_ROWS` operands of one
    structure is turned into one (:func:`~lgshape.tables.find_tables`). Then
    each pruning cell keeps the rows that can matter there, the search
    evaluates only those, and the compiled kernels depend on the templates,
    not on the number of rows or their values. Tables use the ``"interval"``
    search and computed bounds (no hand-given L or G). ``tables=False``
    evaluates the whole expression everywhere instead (the unpruned form, for
    comparison: one fused kernel that grows with the expression).
    ``named_centre``: the box centre enters f's local coordinates as named
    constants, so the compiled kernels do not depend on where the box is
    (for a box that moves with a scene parameter); by default it is folded
    into f's constants where that is exact, which keeps geometry far from
    the origin precise.
    """

    def __init__(self, expr, bbox=None, *, L: float | None = None, G: float | None = None,
                 depth: int | None = None, search: str | None = None,
                 max_iterations: int = 4096, tables: bool = True,
                 named_centre: bool = False):
        f, default_box = _as_expr(expr)
        bbox = bbox if bbox is not None else default_box
        if bbox is None:
            raise ValueError("Surface needs a bbox ((x0, y0, z0), (x1, y1, z1)) for a plain expression")
        lo, hi = _check_box(bbox)
        for name, v in (("L", L), ("G", G)):
            if v is not None and not (isinstance(v, numbers.Real) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive finite number, got {v}")
        if depth is not None:
            _check_int("depth", depth, 2, 10)
        self.max_iterations = _check_int("max_iterations", max_iterations, 1, 2**30)
        if search is None:
            search = "global" if G is not None else "interval"
        if search not in SEARCH_MODES:
            raise ValueError(f"unknown search mode {search!r} (one of {', '.join(SEARCH_MODES)})")
        self.search = search
        if not tables and isinstance(f, TableForm):
            f = f.expr()
        # a table found in a plain expression is an optimisation: not with a
        # hand-given L or G or another search mode, which need the fused form
        fused_only = L is not None or G is not None or search != "interval"
        self.tables = f if isinstance(f, TableForm) else \
            (find_tables(f) if tables and not fused_only else None)
        self._expr = None if isinstance(f, TableForm) else f
        self.depth = _check_int("depth", _default_depth(self.tables, self._expr)
                                if depth is None else depth,
                                2, 10)
        self.lo, self.hi = lo, hi
        if self.tables is not None and (L is not None or G is not None or search != "interval"):
            raise ValueError("a table form (many primitives) uses the 'interval' search with "
                             "computed bounds: leave out L, G and search")
        self._check_defined()
        if L is not None:
            self._check_L(float(L))
        if G is not None:
            self._check_G(float(G))
        self.L, self.G_hand = L, G
        # The search evaluates f about the box centre (see the module notes).
        self.centre = 0.5 * (lo + hi)
        if self.tables is None:
            self.local_expr = localize(f, self.centre, named_centre)
            # f of degree <= 2: its quadratic form along a ray is exact (to
            # rounding), and the search starts from the first root it allows
            self.quadric = f.degree() <= 2
            #: A polynomial of degree 3 to raypoly.MAX_DEGREE: the interval
            #: search works on each ray's polynomial in its parameter
            #: (:mod:`lgshape.expr.raypoly`); False evaluates f's
            #: expression in each test instead.
            #: A sum of products of sines and cosines of affine functions
            #: (:mod:`lgshape.expr.raytrig`: the gyroid, Schwarz's surfaces)
            #: is taken the same way, as each ray's sum of sinusoids.
            polynomial = raypoly.ray_degree(self.local_expr) < math.inf
            self.ray_trig = None if self.quadric or search != "interval" or polynomial \
                else raytrig.trig_sum(self.local_expr)
            self.ray_polynomial = search == "interval" and not self.quadric \
                and (polynomial or self.ray_trig is not None)
            if HORNER and not self.quadric and not self.ray_polynomial:
                # the expression path evaluates f node by node: sums of
                # powers of one subexpression in Horner form
                self.local_expr = horner(self.local_expr)
            self.g_expr, self.h_expr = ray_derivatives(self.local_expr)
            #: f is defined and finite wherever its interval forms are
            #: finite (no division by a variable, sqrt, log or negative
            #: power), so those forms alone may prove g's sign and F's at
            #: an interval's ends (:meth:`_Evaluator._decided`)
            self.total = _total(self.local_expr)
            # the grid's box: the cube about the box (cubic cells, see
            # _grid_box); the search keeps to the box itself
            self.grid = gridmod.build(f, *_grid_box(lo, hi), self.depth,
                                      mode="global" if L is not None else "local", L=L)
            self.cell_rows = None
        else:
            self.quadric = self.ray_polynomial = self.total = False
            self.ray_trig = None
            self.cell_rows = tablemod.build(self.tables, lo, hi, self.depth)
            self.grid = gridmod.brick_map(lo, hi, self.depth, self.cell_rows.cells,
                                          self.cell_rows.tested)
        self._device = {}
        self._frozen = {}
        #: Run standalone queries as frozen functions (see :meth:`trace`);
        #: False traces every call.
        self.freeze = True

    @property
    def expr(self) -> Expr:
        """f as one expression (for a table form, built on first use)."""
        if self._expr is None:
            self._expr = self.tables.expr()
        return self._expr

    # -- construction checks ----------------------------------------------------
    def _check_defined(self):
        p = _sample_points(self.lo, self.hi)
        with np.errstate(all="ignore"):
            if self.tables is not None:
                v = evaluate_points(self.tables, p)
            else:
                v = evaluate(self.expr, {c: p[:, i] for i, c in enumerate("xyz")}, NUMPY)
        if not np.any(np.isfinite(np.broadcast_to(v, len(p)))):
            shown = self.tables if self.tables is not None else self.expr
            raise ValueError(f"f = {shown!r} is NaN or infinite at all {len(p)} sampled "
                             f"points of the box {self.bbox}: it has no surface there")

    def _check_L(self, L):
        p = _sample_points(self.lo, self.hi, seed=1)
        with np.errstate(all="ignore"):
            g = evaluate(list(gradient(self.expr)), {c: p[:, i] for i, c in enumerate("xyz")}, NUMPY)
        norm = np.sqrt(sum(np.broadcast_to(gi, len(p)) ** 2 for gi in g))
        norm = np.where(np.isfinite(norm), norm, -1.0)
        i = int(np.argmax(norm))
        if norm[i] > L:
            raise ValueError(f"L = {L} is too small: |grad f| = {norm[i]:.6g} at "
                             f"{tuple(round(float(c), 6) for c in p[i])} (a valid L bounds "
                             f"|grad f| over the whole box)")

    def _check_G(self, G):
        p = _sample_points(self.lo, self.hi, seed=2)
        H = hessian(self.expr)
        with np.errstate(all="ignore"):
            flat = evaluate([H[i][j] for i in range(3) for j in range(3)],
                            {c: p[:, i] for i, c in enumerate("xyz")}, NUMPY)
        M = np.stack([np.broadcast_to(e, len(p)) for e in flat], -1).reshape(-1, 3, 3)
        ok = np.all(np.isfinite(M), axis=(1, 2))
        lam = np.zeros(len(p))
        lam[ok] = np.abs(np.linalg.eigvalsh(0.5 * (M[ok] + M[ok].transpose(0, 2, 1)))).max(1)
        i = int(np.argmax(lam))
        if lam[i] > G:
            raise ValueError(f"G = {G} is too small: |d^2F/dt^2| reaches {lam[i]:.6g} for a "
                             f"unit direction at {tuple(round(float(c), 6) for c in p[i])} "
                             f"(a valid G bounds the Hessian's norm over the whole box)")

    # -- host-side facts ------------------------------------------------------
    @property
    def bbox(self):
        return tuple(map(float, self.lo)), tuple(map(float, self.hi))

    @property
    def diagonal(self) -> float:
        return float(np.linalg.norm(self.hi - self.lo))

    @property
    def memory_bytes(self) -> int:
        """Size of the pruning structure: the brick map, and the walk's
        dense table up to :data:`lgshape.grid.DENSE_MAX_DEPTH` (four bits a
        fine cell), with its eight octant tables up to
        :data:`lgshape.grid.OCTANT_MAX_DEPTH`."""
        tables = (9 if self.depth <= gridmod.OCTANT_MAX_DEPTH else 1) \
            if self.depth <= gridmod.DENSE_MAX_DEPTH else 0
        return self.grid.nbytes + tables * self.grid.resolution ** 3 // 2

    def global_G(self) -> float:
        """G for unit directions: the hand-given one, else the Hessian norm over the box."""
        if self.G_hand is not None:
            return self.G_hand
        return float(bounds.hessian_norm(self.expr, self.lo[None], self.hi[None])[0])

    def __repr__(self):
        shown = self.tables if self.tables is not None else self.expr
        return (f"Surface({shown!r}, bbox={self.bbox}, depth={self.depth}, "
                f"cells={len(self.grid.cells)})")

    # -- Dr.Jit side ------------------------------------------------------------
    def _kernel_data(self, Float):
        key = Float
        if key not in self._device:
            import drjit as dr
            Float64 = dr.float64_array_t(Float)
            dev = gridmod.DeviceGrid(self.grid, Float)
            self._device[key] = _KernelData(
                m=DrJitMath(Float), m64=DrJitMath(Float64), grid=dev,
                lo=[dr.opaque(Float64, float(v)) for v in self.lo],
                hi=[dr.opaque(Float64, float(v)) for v in self.hi],
                centre=[dr.opaque(Float64, float(v)) for v in self.centre],
                grid_origin=[dr.opaque(Float64, float(v)) for v in self.centre - self.grid.lo],
                diag=dr.opaque(Float, self.diagonal),
                tables=None if self.tables is None else DeviceTables(
                    self.tables, self.cell_rows, self.grid, self.centre, Float))
        return self._device[key]

    def gradient(self, p):
        """grad f at points p (Array3f or (N, 3) numpy)."""
        p = _points(p)
        Float = type(p.x)
        K = self._kernel_data(Float)
        if K.tables is not None:
            _, _, g = _table_point(K, p, with_gradient=True)
            return type(p)(*(Float(v) for v in g))
        gx, gy, gz = evaluate(list(gradient(self.expr)), {"x": p.x, "y": p.y, "z": p.z}, K.m)
        return type(p)(gx, gy, gz)

    def normal(self, p):
        """The unit normal grad f / |grad f| (towards f > 0)."""
        import drjit as dr
        g = self.gradient(p)
        n2 = dr.squared_norm(g)
        return dr.select(n2 > 0, g * dr.rsqrt(n2), type(g)(0, 0, 1))

    def value(self, p):
        """f at points p."""
        p = _points(p)
        K = self._kernel_data(type(p.x))
        if K.tables is not None:
            return type(p.x)(_table_point(K, p)[0])
        return evaluate(self.expr, {"x": p.x, "y": p.y, "z": p.z}, K.m)

    def intersect(self, o, d, t_min=0.0, t_max=math.inf, active=True):
        """Nearest root t in [t_min, t_max] along o + t d: returns (t, hit),
        t = inf where there is none."""
        r = self.trace(o, d, t_min, t_max, active)
        return r.t, r.hit

    def occluded(self, o, d, t_max, active=True, t_min=0.0):
        """Any root in [t_min, t_max]? Stops at the first proven root."""
        return self.trace(o, d, t_min, t_max, active, any_hit=True).hit

    def trace(self, o, d, t_min=0.0, t_max=math.inf, active=True, any_hit=False) -> RayResult:
        """The search with its per-ray statistics (see :class:`RayResult`).

        ``o``, ``d``: Dr.Jit Array3f (any backend) or numpy arrays of shape
        (N, 3) (one ray: (3,)); t_min, t_max, active: scalars or arrays of N.
        Arrays of one ray broadcast against N; other mismatched sizes raise
        ValueError. Empty input gives empty output.

        A standalone query (Dr.Jit rays, outside a symbolic loop, call or
        conditional; t_min, t_max and active Python scalars or Dr.Jit arrays)
        runs as a frozen function (``dr.freeze``): its first call for a ray
        count and argument layout traces the search, later ones launch the
        recorded kernels without tracing it again (the tracing costs 1-4 ms
        a call, as much as the search of a 512^2 frame on simple surfaces).
        Its inputs are evaluated first and its outputs are evaluated arrays.
        ``freeze = False`` traces every call (inside symbolic code it always
        does, and its work fuses with the caller's)."""
        o, d, n = _rays(o, d, t_min, t_max, active)
        if n == 0:
            return _empty_result(type(o.x))
        if self.freeze and _freezable(o, d, t_min, t_max, active):
            return call_frozen(self._frozen_search(any_hit),
                               self._kernel_data(type(o.x)), o, d, t_min, t_max, active, n)
        return _search(self, o, d, t_min, t_max, active, any_hit)

    def _frozen_search(self, any_hit):
        """The search as a frozen function, one per query kind. Its inputs:
        the kernel data (so that the grid, the tables and the opaque
        constants are read on every launch), the rays, and the ray count
        (recorded kernels are sized by it); one per setting of
        ``ray_polynomial`` too (the recording holds the path it took)."""
        key = (any_hit, self.ray_polynomial)
        fn = self._frozen.get(key)
        if fn is None:
            import drjit as dr

            def search(K, o, d, t_min, t_max, active, n):
                return _search(self, o, d, t_min, t_max, active, any_hit)
            fn = self._frozen[key] = dr.freeze(search, limit=FREEZE_LIMIT, warn_after=2**30)
        return fn


@dataclass
class _KernelData:
    """A Surface's device-side constants for one backend (opaque, so a new
    value does not recompile)."""
    m: object            # DrJitMath, float32 (intervals)
    m64: object          # DrJitMath, float64 (point values)
    grid: object         # gridmod.DeviceGrid
    lo: list             # box, float64
    hi: list
    centre: list         # origin of the local coordinates, float64
    grid_origin: list    # centre - lo: local coordinates -> grid coordinates
    diag: object         # box diagonal, float32
    tables: object = None   # tables.DeviceTables of a table form


def _table_point(K, p, with_gradient=False):
    """f (and grad f) of a table form at points p, over the rows of the cell
    each point lies in (every row where it lies in no occupied cell)."""
    import drjit as dr
    Float64 = K.m64.Float
    env, err = {}, {}
    for i, v in enumerate("xyz"):
        env[v] = Float64(p[i]) - K.centre[i]          # local coordinates
        err[v] = K.m64.u * dr.abs(env[v])
    Float = type(p.x)
    slot, occupied = gridmod.slot_at(K.grid, [Float(env[v] + K.grid_origin[i])
                                              for i, v in enumerate("xyz")], K.tables.up)
    all_rows = K.tables.all_rows(dr.width(p.x))
    cell_rows = K.tables.ranges(slot, occupied)
    rng = [(dr.select(occupied, s, s0), dr.select(occupied, e, e0))
           for (s, e), (s0, e0) in zip(cell_rows, all_rows)]
    dirs = [{"dx": float(a == 0), "dy": float(a == 1), "dz": float(a == 2)}
            for a in range(3)] if with_gradient else [{"dx": 0.0, "dy": 0.0, "dz": 0.0}]
    env.update(dirs[0])
    return K.tables.point(env, err, rng, K.m64, directions=dirs)


# ---------------------------------------------------------------------------
# Inputs
# ---------------------------------------------------------------------------

def _width(v):
    import drjit as dr
    if isinstance(v, np.ndarray):
        return v.size if v.ndim else 1
    return dr.width(v) if dr.is_array_v(v) else 1


def _points(p):
    """Points as a Dr.Jit Array3f (numpy input: (N, 3) or (3,))."""
    import drjit as dr
    if dr.is_array_v(p):
        return p
    a = _as_n3(p, "p")
    return default_array3f()(np.ascontiguousarray(a.T))


def default_array3f():
    """The Array3f that numpy points and rays become: the backend of
    Mitsuba's variant when a CUDA one is set, else LLVM."""
    mi = sys.modules.get("mitsuba")
    try:
        cuda = mi is not None and mi.variant() is not None and mi.variant().startswith("cuda")
    except (AttributeError, ImportError):          # no variant module loaded yet
        cuda = False
    if cuda:
        from drjit.cuda.ad import Array3f
    else:
        from drjit.llvm.ad import Array3f
    return Array3f


def _as_n3(v, name):
    a = np.asarray(v, dtype=np.float32)
    if a.ndim == 1 and a.shape[0] == 3:
        a = a[None]
    if a.ndim != 2 or a.shape[1] != 3:
        hint = " (it looks transposed: pass (N, 3))" if a.ndim == 2 and a.shape[0] == 3 else ""
        raise ValueError(f"{name} must be an (N, 3) array or a Dr.Jit Array3f, "
                         f"got shape {a.shape}{hint}")
    return a


def _rays(o, d, t_min, t_max, active):
    """Checked ray arrays: (o, d, n) with o, d Dr.Jit Array3f."""
    import drjit as dr
    if not dr.is_array_v(o) or not dr.is_array_v(d):
        # numpy beside a Dr.Jit array takes that array's type (and backend)
        Array3f = (type(o) if dr.is_array_v(o) else type(d) if dr.is_array_v(d)
                   else default_array3f())
        conv = []
        for name, v in (("o", o), ("d", d)):
            if dr.is_array_v(v):
                conv.append(v)
            else:
                conv.append(Array3f(np.ascontiguousarray(_as_n3(v, name).T)))
        o, d = conv
    sizes = {"o": dr.width(o), "d": dr.width(d), "t_min": _width(t_min),
             "t_max": _width(t_max), "active": _width(active)}
    n = max(sizes.values())
    if min(sizes["o"], sizes["d"]) == 0:
        n = 0
    bad = {k: v for k, v in sizes.items() if v not in (1, n)}
    if bad and n:
        k = next(iter(bad))
        other = "o" if k != "o" and sizes["o"] == n else "d"
        raise ValueError(f"mismatched sizes: {k} has {bad[k]} rays, {other} has {n}")
    return o, d, n


def _freezable(o, d, t_min, t_max, active):
    """May this query run frozen? Dr.Jit rays (JIT backend, no gradients)
    outside symbolic code, and the other arguments Python scalars or Dr.Jit
    arrays."""
    import drjit as dr
    if not dr.is_jit_v(o) or dr.grad_enabled(o, d) or dr.flag(dr.JitFlag.SymbolicScope):
        return False
    return all(dr.is_array_v(v) or isinstance(v, (bool, numbers.Real))
               for v in (t_min, t_max, active))


def call_frozen(fn, *args):
    """fn(*args) for a frozen function, with Python's cyclic garbage
    collector held off: a collection while it records could free arrays
    that map host memory, which Dr.Jit 1.5 does not allow then (it aborts
    the process)."""
    import gc
    enabled = gc.isenabled()
    gc.disable()
    try:
        return fn(*args)
    finally:
        if enabled:
            gc.enable()


def _empty_result(Float):
    import drjit as dr
    Float64 = dr.float64_array_t(Float)
    return RayResult(Float(), dr.mask_t(Float)(), dr.uint32_array_t(Float)(),
                     dr.uint32_array_t(Float)(), dr.mask_t(Float)(), dr.mask_t(Float)(),
                     Float64())


# ---------------------------------------------------------------------------
# The search
# ---------------------------------------------------------------------------

# The search, in phases (each a function of its own):
#
#   walk    (_walk) the DDA to the next occupied cell, a nested loop of its
#           own (lgshape.grid.Walker);
#   search  (_step) one evaluation per iteration: the interval test of the
#           whole cell first (most cells end there: excluded, or monotone
#           with or without a sign change), then the stackless bisection of
#           the cells it leaves open; ends with a bracket, a proven root or
#           none in the cell (walk on);
#   refine  (_refine) safeguarded Newton in the bracket, in a loop of its
#           own after the search, on the rays that found one.
#
# _locate runs walk and search in one symbolic loop: lanes of one SIMD packet
# walking and searching share its iterations (measured: faster than a loop
# over cells that waits for the whole packet in each phase). Refinement needs
# none of the search's state, so it runs after it with five variables (Dr.Jit
# merges every state variable of a symbolic loop with a select per iteration).

# Outcomes of a ray's search (_Lane.outcome; WALKING while it goes on).
WALKING, NONE, BRACKET, HIT, CAPPED = range(5)

#: The segment the walk hands the search (interval mode, plain
#: expressions): from the entry of the next occupied cell over at least
#: this many edges of the smallest cell, whatever the cells after the first
#: one hold (an empty cell in it costs nothing to prove: the bounds exclude
#: it). One test decides it where f is simple along it; the bisection
#: splits it where not. The walk does not step through the cells inside it
#: (a dependent gather each): 1.2-1.45x faster than runs of up to 8
#: occupied cells walked one by one, which were 1.1-1.3x faster than one
#: cell at a time. A table form takes one cell at a time (each cell has its
#: own rows), and so do the seed's modes ("taylor", "global"), whose test
#: |g(t_m)| > G r needs short intervals: over runs, some simple roots were
#: only decided at the minimum width.
SPAN_CELLS = 8

#: On the expression path, no point value of F where F's quadratic forms
#: decide the interval alone (:meth:`_Evaluator._decided`); a packet skips
#: the point's evaluation when none of its lanes needs it. Measured against
#: False (one process, interleaved, same hits; t within 1e-9 x diag):
#: blobs camera / incoherent / shadow rays 1.03-1.09x / 1.05x / 1.20x,
#: spikes 1.04-1.07x / 1.03-1.17x / 1.15-1.19x.
FORM_DECIDES = True


@dataclass
class _Rays:
    """The per-ray constants of one search: the ray moved to its box entry
    in the box's local coordinates, u(s) = e + s d for s in [0, span], and
    the widths that scale with the ray's speed."""
    e64: list            # entry point, float64
    d64: list            # direction, float64
    e32: list            # the same in float32 (intervals)
    d32: list
    g_org: list          # entry point relative to the grid's lower corner
    span: object         # Float: length of the segment in the box, in s
    margin: object       # Float: overlap of neighbouring cell segments
    cell_len: object     # Float: the smallest cell's edge, in s
    r_min: object        # Float: minimum half width of a search interval
    tol: object          # Float64: refinement tolerance in s
    entering: object     # Bool: the ray enters the box from outside (the walk's tables)


class _Evaluator:
    """F, g and their bounds along the rays for one Surface and backend:
    point values in float64 with error bounds, float32 intervals over
    segments, and the Kalra-Barr test of one interval (:meth:`test`)."""

    def __init__(self, surf, K, rays: _Rays):
        import drjit as dr
        self.dr = dr
        self.surf, self.K, self.rays, self.mode = surf, K, rays, surf.search
        self.tabled = K.tables is not None
        if not self.tabled:
            self.f, self.ge, self.he = surf.local_expr, surf.g_expr, surf.h_expr
        Float = K.m.Float
        if self.mode == "global":
            d = rays.d32
            self.G_glob = K.m64.Float(dr.opaque(Float, surf.global_G())
                                      * (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]))
        self.dirs = {"dx": rays.d64[0], "dy": rays.d64[1], "dz": rays.d64[2]}
        # F's coefficients along each ray (a polynomial f), once per ray
        self.poly = self.trig = None
        if self.mode == "interval" and not self.tabled and surf.ray_polynomial:
            if surf.ray_trig is not None:
                # F's sinusoids along each ray, once per ray
                self.trig = raytrig.ray_sinusoids(surf.ray_trig, rays.e64, rays.d64, K.m64)
            else:
                # F's coefficients along each ray (a polynomial f), once per ray
                self.poly = raypoly.ray_polynomial(self.f, rays.e64, rays.d64, K.m64)

    def _point_env(self, s):
        """The ray's point at s (float64) and the rounding of its coordinates."""
        dr, R, u = self.dr, self.rays, self.K.m64.u
        s = self.K.m64.Float(s)
        env, err = dict(self.dirs), {}
        for i, v in enumerate("xyz"):
            sd = s * R.d64[i]
            env[v] = R.e64[i] + sd
            err[v] = u * (dr.abs(sd) + dr.abs(env[v]))
        return env, err

    def point_and_bounds(self, s, lo, hi, rng, need, want=True):
        """:meth:`point` at s and the float32 bounds over [lo, hi] where
        ``need`` (of :meth:`_bounds`, less the slope, which stands for g's
        point value in the interval mode); a table form's, the ranges of g
        and F, in one loop over the cell's rows with the point values
        (every lane: each row's parameters are gathered once). Returns
        (point, bounds, c2): c2, the curvature of F's quadratic form at the
        middle (interval mode; 0 elsewhere), for the start of Newton.

        ``want``: the lanes that use the point (its value elsewhere is not
        read). The point is (F, eF, g, eg, decided): ``decided`` (the
        interval mode on a fused expression; else None), the lanes whose
        interval F's forms decide alone, with that decision
        (:meth:`_decided`), where F's point value was not evaluated and F
        is the form's value at s."""
        K, R = self.K, self.rays
        if self.poly is not None or self.trig is not None:
            return self._poly_point_and_bounds(s, lo, hi, need)
        if self.tabled:
            env, err = self._point_env(s)
            F, eF, g, B = K.tables.point_segment(env, err, rng, K.m64, R.e32, R.d32, lo, hi, K.m)
            return (F, eF, g, None, None), B, 0.0
        if self.mode == "interval":
            # g's value only starts Newton in a bracket: the slope of F's
            # quadratic form at the middle (float32) serves, so the point
            # here is F's alone, unless an interval rule flattened the form
            # (c1 = 0: sqrt, an SDF's distance)
            B = self._bounds(lo, hi, need)
            Float64 = K.m64.Float
            c1, c2, c0 = B[4:7]
            B = B[:4] + B[7:]
            flat = need & (c1 == 0)
            decided, known = None, None
            if FORM_DECIDES:
                lanes, empty, s_lo = self._decided(B)
                decided = (need & ~flat & lanes, empty, s_lo)
                known = want & ~decided[0]
            F, eF, g, _ = self.point(s, rng, g_where=flat, where=known)
            if known is not None:
                F = self.dr.select(known, F, Float64(c0))
            return (F, eF, self.dr.select(flat, g, Float64(c1)), None, decided), B, \
                self.dr.select(flat, 0.0, Float64(c2))
        F, eF, g, eg = self.point(s, rng)
        return (F, eF, g, eg, None), self._bounds(lo, hi, need), 0.0

    def _decided(self, B):
        """What F's forms decide without F's point value (interval mode;
        B: the ranges of g's and F's forms, and F's at the two ends):
        (lanes, empty, s_lo). On ``lanes``, F's range excludes 0 (no root
        where f is defined), or, for an f defined everywhere
        (:attr:`Surface.total`: then finite forms mean F is finite on the
        interval), g keeps one sign and F's signs at the two ends are known:
        the same, no root; opposite, one root in the whole interval, whose
        left end has F's sign ``s_lo``. ``empty``: no root."""
        dr = self.dr
        g_lo, g_hi, F_lo, F_hi, Fa_lo, Fa_hi, Fb_lo, Fb_hi = B
        excluded = (F_lo > 0) | (F_hi < 0)
        s_a, s_b = _sign_of(Fa_lo, Fa_hi), _sign_of(Fb_lo, Fb_hi)
        lanes = excluded
        if self.surf.total:
            monotone = ((g_lo > 0) | (g_hi < 0)) & dr.isfinite(g_lo) & dr.isfinite(g_hi)
            lanes = lanes | (monotone & (s_a != 0) & (s_b != 0)
                             & dr.isfinite(F_lo) & dr.isfinite(F_hi))
        return lanes, excluded | (s_a == s_b), s_a

    def _poly_point_and_bounds(self, s, lo, hi, need):
        """:meth:`point_and_bounds` from the ray's polynomial (its
        coefficients shifted to s) or its sinusoids (their values and
        derivatives at s): F(s) with its error bound, F's slope and
        curvature there, and F's and g's quadratic forms over the
        interval's half width r (as :meth:`test` rounds it), whose
        remainders are the higher terms (s: the interval's middle where
        ``need``)."""
        dr, m64 = self.dr, self.K.m64
        Float64 = m64.Float
        t = Float64(s)
        r = Float64(_half_width(lo, hi))
        seg = Segment(m64, r)
        if self.trig is not None:
            Qf, Qg, F, eF = raytrig.forms(seg, self.trig, t, self.surf.ray_trig.sinusoids)
            g, c2 = Qf.c1, Qf.c2
        else:
            c, w = self.poly
            cs, W = raypoly.shift(m64, c, w, t)
            at = dr.abs(t)
            Qf, Qg = raypoly.forms(seg, cs, W, at)
            F, eF = cs[0], raypoly.bound(m64, W, at)
            g, c2 = cs[1], cs[2]
        Fq, gq = quad_range(seg, Qf), quad_range(seg, Qg)
        inf = Float64(dr.inf)
        B = tuple(dr.select(need, v, dflt) for v, dflt in
                  zip((gq.lo, gq.hi, Fq.lo, Fq.hi)
                      + quad_ends(seg, Qf, at=_end_offset(lo, hi)),
                      (0.0, 0.0, -inf, inf, -inf, inf, -inf, inf)))
        # F(s): the coefficient's bound is the whole ray's rounding; where
        # it leaves the sign unknown (near a root), f's own float64 point
        # value, whose bound is the rounding at that point, decides (both
        # enclose the same exact value; a branch a packet takes only where
        # one of its lanes needs it)

        def at_point(s, F, eF):
            env, err = self._point_env(s)
            return evaluate_with_error(self.f, env, err, m64)
        F, eF = dr.if_stmt(args=(t, F, eF), cond=~(dr.abs(F) > eF), true_fn=at_point,
                           false_fn=lambda s, F, eF: (F, eF), label="lgshape_point")
        return (F, eF, g, None, None), B, c2

    def point(self, s, rng, g_where=None, where=None):
        """F and g at s in float64 with error bounds of F (and of g where the
        search mode uses g's value in a proof). ``g_where`` (interval mode):
        g only on those lanes (0 elsewhere), in a branch a packet takes only
        where one of its lanes needs it; ``where`` (interval mode): F only
        on those lanes (0 elsewhere), in such a branch too."""
        K = self.K
        m64 = K.m64
        env, err = self._point_env(s)
        if self.tabled:
            F, eF, (g,) = K.tables.point(env, err, rng, m64)
            return F, eF, g, None
        if self.mode == "interval":
            # g's point value only steers Newton: no error bound needed.
            if where is None:
                F, eF = evaluate_with_error(self.f, env, err, m64)
            else:
                F, eF = self.dr.if_stmt(
                    args=(s,), cond=where,
                    true_fn=lambda s: evaluate_with_error(self.f, env, err, m64),
                    false_fn=lambda s: (m64.Float(0), m64.Float(0)), label="lgshape_point")
            if g_where is None:
                return F, eF, evaluate(self.ge, env, m64), None
            g = self.dr.if_stmt(args=(s,), cond=g_where,
                                true_fn=lambda s: evaluate(self.ge, env, m64),
                                false_fn=lambda s: m64.Float(0), label="lgshape_slope")
            return F, eF, g, None
        (F, eF), (g, eg) = evaluate_with_error([self.f, self.ge], env, err, m64)
        return F, eF, g, eg

    def steer(self, s, rng):
        """F and g at s (float64) for Newton's steps, without error bounds:
        from the ray's coefficients (Horner) for a polynomial f, its
        sinusoids for a sum of sines and cosines, else :meth:`point`."""
        if self.trig is not None:
            return raytrig.value_and_slope(self.K.m64, self.trig, self.K.m64.Float(s),
                                           self.surf.ray_trig.sinusoids)
        if self.poly is None:
            F, _, g, _ = self.point(s, rng)
            return F, g
        return raypoly.value_and_slope(self.poly[0], self.K.m64.Float(s))

    def _bounds(self, lo, hi, need):
        """Float32 bounds over the segment e + [lo, hi] d where ``need`` (a
        fused expression; a table form's come from :meth:`point_and_bounds`):
        in the interval mode (g_lo, g_hi, F_lo, F_hi, c1, c2, c0, Fa_lo,
        Fa_hi, Fb_lo, Fb_hi): the ranges of g's and F's quadratic forms, the
        slope, curvature and value of F's form at the middle, and its bounds
        at the two ends; in the Taylor mode (S_lo, S_hi), h's interval."""
        dr, K, R = self.dr, self.K, self.rays
        m, Float = K.m, K.m.Float
        if self.mode == "interval":
            def true_fn(lo, hi):
                seg, env = quad_env(m, R.e32, R.d32, lo, hi)
                memo = {}
                (Qf,) = evaluate_quadratic([self.f], env, seg, memo)
                Fq = quad_range(seg, Qf)
                # g's form (its range) only where F's does not exclude a
                # root: in a branch a packet takes where a lane needs it,
                # on the nodes f's form left in the memo
                needs_g = need & (Fq.lo <= 0) & (Fq.hi >= 0)

                def g_range(lo, hi):
                    (Qg,) = evaluate_quadratic([self.ge], env, seg, memo)
                    gq = quad_range(seg, Qg)
                    return gq.lo, gq.hi
                gq = iv.Interval(*dr.if_stmt(
                    args=(lo, hi), cond=needs_g, true_fn=g_range,
                    false_fn=lambda lo, hi: (Float(-dr.inf), Float(dr.inf)),
                    label="lgshape_slope_form"))
                # the ends' values inside [lo, hi]: seg.r reaches past
                # them, by its rounding up (2^-21) and the rounding of the
                # middle tm (an ulp of tm, 2^-23 |tm|)
                at = dr.maximum(seg.r * (1 - 2.0**-19)
                                - dr.abs(0.5 * (lo + hi)) * 2.0**-21, 0.0)
                return (gq.lo, gq.hi, Fq.lo, Fq.hi, Qf.c1, Qf.c2, Qf.c0) \
                    + quad_ends(seg, Qf, at=at)
            inf = Float(dr.inf)
            return dr.if_stmt(args=(lo, hi), cond=need, true_fn=true_fn,
                              false_fn=lambda lo, hi: (Float(0), Float(0), -inf, inf, Float(0),
                                                       Float(0), Float(0), -inf, inf, -inf, inf),
                              label="lgshape_bounds")
        def true_fn(lo, hi):
            Si = bounds.segment_interval(self.he, R.e32, R.d32, lo, hi, m)
            return Si.lo, Si.hi
        return dr.if_stmt(args=(lo, hi), cond=need, true_fn=true_fn,
                          false_fn=lambda lo, hi: (Float(0), Float(0)), label="lgshape_bounds")

    def clip(self, lo, hi, active):
        """What F's quadratic form over the segment [lo, hi] tells
        (interval mode, plain expression; :func:`quad_clip`): (free, first,
        crossed, b_lo, b_hi, s_lo). ``free``: no root; else no root before
        ``first`` (float32, rounded down); ``crossed``: f continuous (a
        polynomial) and of the other sign at b_hi, so the first root is in
        the bracket [b_lo, b_hi] (float64), where F's sign is s_lo at b_lo."""
        dr, K, R = self.dr, self.K, self.rays
        Float64 = K.m64.Float
        seg, env = quad_env(K.m, R.e32, R.d32, lo, hi)
        (Qf,) = evaluate_quadratic([self.f], env, seg)
        free, s_first, s_cross, crossed, up = quad_clip(seg, Qf)
        tm = 0.5 * (lo + hi)
        first = tm + s_first
        first = dr.maximum(first - dr.abs(first) * 2.0**-22, lo)
        # the bracket at the points the proofs hold for (float64, outward)
        b_lo = _down(Float64(tm) + Float64(s_first))
        b_hi = _up(Float64(tm) + Float64(s_cross))
        s_lo = dr.select(up, 1, -1)
        # (the root must lie in the ray's range [lo, hi] too)
        crossed = active & ~free & crossed & (b_lo >= Float64(lo)) & (b_hi <= Float64(hi))
        return active & free, dr.select(active, first, lo), crossed, b_lo, b_hi, s_lo

    def _natural(self, lo, hi, need):
        """Float32 interval of F over the segment, where ``need``."""
        dr, K, R = self.dr, self.K, self.rays
        Float = K.m.Float

        def true_fn(lo, hi):
            Fi = bounds.segment_interval(self.f, R.e32, R.d32, lo, hi, K.m)
            return Fi.lo, Fi.hi
        return dr.if_stmt(args=(lo, hi), cond=need, true_fn=true_fn,
                          false_fn=lambda lo, hi: (Float(-dr.inf), Float(dr.inf)),
                          label="lgshape_natural")

    def test(self, lo, hi, rng, active, at, bounds):
        """The Kalra-Barr test of the ray interval [lo, hi] (float32 ends)
        on the lanes ``active``, from the point values at its middle (``at``)
        and the bounds over it (``bounds``), both from
        :meth:`point_and_bounds`. See :class:`_Test`."""
        dr = self.dr
        Float64 = self.K.m64.Float
        # [tm - r, tm + r] must cover [lo, hi]: the midpoint in float64
        # (exact), the half width rounded outward.
        tm = 0.5 * (Float64(lo) + Float64(hi))
        r = _half_width(lo, hi)
        re = _end_offset(lo, hi)
        F, eF, g, eg, decided = at
        local = active & (self.mode != "global")
        S_lo, S_hi, *Fn = (Float64(v) for v in bounds)
        defined = dr.isfinite(F) & dr.isfinite(eF)
        Fm_lo, Fm_hi = F - eF, F + eF
        r64 = Float64(r)
        if self.mode == "interval":
            # Mean-value form: F(t) in F(t_m) + [g] [-r, r].
            g_lo, g_hi = S_lo, S_hi
            mv_lo = _down(Fm_lo + dr.minimum(r64 * g_lo, -r64 * g_hi))
            mv_hi = _up(Fm_hi + dr.maximum(r64 * g_hi, -r64 * g_lo))
            Fa = (_down(Fm_lo - re * g_hi), _up(Fm_hi - re * g_lo))
            Fb = (_down(Fm_lo + re * g_lo), _up(Fm_hi + re * g_hi))
        else:
            # Second-order Taylor form with G >= |h|: the seed's |g(t_m)| > G r.
            h_lo, h_hi = (S_lo, S_hi) if self.mode == "taylor" else (-self.G_glob, self.G_glob)
            G = dr.maximum(dr.abs(h_lo), dr.abs(h_hi))
            q2 = 0.5 * r64 * r64
            gm_lo, gm_hi = g - eg, g + eg
            ag = dr.maximum(dr.abs(gm_lo), dr.abs(gm_hi)) * r64
            g_lo, g_hi = _down(gm_lo - G * r64), _up(gm_hi + G * r64)
            mv_lo = _down(Fm_lo - ag + dr.minimum(h_lo, 0) * q2)
            mv_hi = _up(Fm_hi + ag + dr.maximum(h_hi, 0) * q2)
            qe = 0.5 * re * re
            Fa = (_down(Fm_lo - gm_hi * re + h_lo * qe), _up(Fm_hi - gm_lo * re + h_hi * qe))
            Fb = (_down(Fm_lo + gm_lo * re + h_lo * qe), _up(Fm_hi + gm_hi * re + h_hi * qe))
        # F over the interval: the mean-value form where it is finite (F(t_m)
        # defined, its derivative bounded), intersected with the range of F's
        # quadratic form (interval mode), or, where neither is finite
        # (undefined points, domain edges, poles), the natural interval form,
        # which also tells whether F is bounded there. A table form's
        # quadratic form stands for both.
        mv_ok = defined & dr.isfinite(mv_lo) & dr.isfinite(mv_hi)
        if Fn and not self.tabled:
            # the quadratic form's range of F; the natural form only where
            # neither it nor the mean-value form is finite
            Fq_lo, Fq_hi = Fn[:2]
            q_ok = dr.isfinite(Fq_lo) & dr.isfinite(Fq_hi)
            need_fi = active & ~mv_ok & ~q_ok
            Fi_lo, Fi_hi = (Float64(v) for v in self._natural(lo, hi, need_fi))
            Fi_lo = dr.maximum(Fi_lo, Fq_lo)
            Fi_hi = dr.minimum(Fi_hi, Fq_hi)
        else:
            need_fi = active & ~mv_ok
            Fi_lo, Fi_hi = Fn if self.tabled else (Float64(v) for v in self._natural(lo, hi, need_fi))
        evals = 1 + dr.select(local, 1, 0) + (0 if self.tabled else dr.select(need_fi, 1, 0))
        F_lo = dr.select(mv_ok, dr.maximum(mv_lo, Fi_lo), Fi_lo)
        F_hi = dr.select(mv_ok, dr.minimum(mv_hi, Fi_hi), Fi_hi)
        F_lo = dr.select(dr.isnan(F_lo), -dr.inf, F_lo)
        F_hi = dr.select(dr.isnan(F_hi), dr.inf, F_hi)
        excluded = (F_lo > 0) | (F_hi < 0)
        # Monotone: g keeps one sign, with finite bounds (an unbounded g may
        # hide a pole or the edge of f's domain).
        monotone = defined & ((g_lo > 0) | (g_hi < 0)) & dr.isfinite(g_lo) & dr.isfinite(g_hi)
        s_a, s_b, s_m = _sign_of(*Fa), _sign_of(*Fb), _sign_of(Fm_lo, Fm_hi)
        if len(Fn) == 6:        # (Fq_lo, Fq_hi, Fa_lo, Fa_hi, Fb_lo, Fb_hi)
            # the quadratic form's values at the ends (second order, where
            # the mean-value form is first order); the two are at points an
            # ulp or so apart, so a disagreement leaves the sign unknown
            s_a = _either_sign(s_a, _sign_of(Fn[2], Fn[3]))
            s_b = _either_sign(s_b, _sign_of(Fn[4], Fn[5]))
        left = monotone & (s_m != 0) & (s_a == -s_m)
        right = monotone & ~left & (s_m != 0) & (s_b == -s_m)
        # F(t_m) within its error bound of 0 (a root at the middle, to
        # rounding), the ends of opposite signs: one root, in the whole
        # interval (else it would split down to the minimum width)
        whole = monotone & (s_m == 0) & (s_a != 0) & (s_b == -s_a)
        empty = active & (excluded | (monotone & (s_m != 0) & (s_a == s_m) & (s_b == s_m)))
        bracket = active & ~empty & (left | right | whole)
        # a sign change with F continuous (g bounded): some root, maybe
        # several (enough for an any-hit query)
        crossing = active & ~empty & defined & dr.isfinite(g_lo) & dr.isfinite(g_hi) \
            & ((s_a * s_b < 0) | (s_a * s_m < 0) | (s_m * s_b < 0))
        b_lo, b_hi = dr.select(right, tm, Float64(lo)), dr.select(left, tm, Float64(hi))
        b_sign = dr.select(right, s_m, s_a)
        if decided is not None:
            # lanes without F's point value: F's forms decided the interval
            # (_Evaluator._decided): no root, or one in the whole interval
            lanes, q_empty, q_sign = decided
            skip = active & lanes
            empty = dr.select(skip, q_empty, empty)
            bracket = dr.select(skip, ~q_empty, bracket)
            crossing = dr.select(skip, ~q_empty, crossing)
            b_lo = dr.select(skip, Float64(lo), b_lo)
            b_hi = dr.select(skip, Float64(hi), b_hi)
            b_sign = dr.select(skip, q_sign, b_sign)
            s_m = dr.select(skip, 0, s_m)
            evals = evals - dr.select(skip, 1, 0)
        return _Test(
            r=r, s_m=s_m, empty=empty, bracket=bracket,
            open=active & ~empty & ~bracket,
            # the bracket: the left half, the right half or the whole, and
            # its left end's sign
            b_lo=b_lo, b_hi=b_hi, b_sign=b_sign,
            g_min=dr.select(monotone, dr.minimum(dr.abs(g_lo), dr.abs(g_hi)), 0.0),
            crossing=crossing,
            defined=defined,
            # F bounded over the interval: no pole inside it
            bounded=mv_ok | (dr.isfinite(Fi_lo) & dr.isfinite(Fi_hi)),
            evals=evals)


@dataclass
class _Test:
    """The outcome of one interval test (Dr.Jit arrays per lane)."""
    r: object            # Float: half width (rounded outward)
    s_m: object          # Int32: sign of F(tm) outside its error bound (0: unknown)
    empty: object        # Bool: no root in the interval
    bracket: object      # Bool: exactly one root, in [b_lo, b_hi]
    open: object         # Bool: undecided
    b_lo: object
    b_hi: object
    b_sign: object       # Int32: sign of F at b_lo
    g_min: object        # Float64: min |g| over the interval where g keeps one sign, else 0
    crossing: object     # Bool: F changes sign, continuously: a root
    defined: object      # Bool: F(tm) defined
    bounded: object      # Bool: F bounded over the interval
    evals: object        # point plus interval evaluations made


def _half_width(lo, hi):
    """The half width r of [lo, hi] (float32 ends) that the test's
    enclosures cover: [tm - r, tm + r] holds [lo, hi] (float32, rounded
    outward), tm = (lo + hi) / 2 in float64."""
    import drjit as dr
    Float64 = dr.float64_array_t(type(lo))
    return type(lo)(0.5 * (Float64(hi) - Float64(lo))) * (1 + 2.0**-22)


def _end_offset(lo, hi):
    """How far from the middle tm = (lo + hi) / 2 (float64) the test takes
    F's signs at the ends of [lo, hi] (float32): the half width, a little
    less, so that tm -+ it lies inside [lo, hi]. The half width r that the
    enclosures cover is rounded up instead, past the ends; a sign taken
    there (say at tm - r, before lo) is not F's at lo: on the first
    interval of a ray leaving the surface it saw the root just behind the
    origin (found on the torus, test_12), and the bracket [lo, tm] held no
    root."""
    import drjit as dr
    Float64 = dr.float64_array_t(type(lo))
    return 0.5 * (Float64(hi) - Float64(lo)) * (1 - 2.0**-50)


def _sign_of(lo, hi):
    """+1 / -1 where [lo, hi] has one strict sign, else 0 (NaN: 0)."""
    import drjit as dr
    return dr.select(lo > 0, 1, dr.select(hi < 0, -1, 0))


def _either_sign(s1, s2):
    """The sign two bounds tell (0 where neither does, or they disagree)."""
    import drjit as dr
    return dr.select(s1 == 0, s2, dr.select((s2 != 0) & (s2 != s1), 0, s1))


def _sign_known(F, eF):
    """Sign of a point value outside its error bound; 0 where it cannot be
    told from 0; 2 where F is undefined (NaN or infinite) or its error bound
    overflows (the value cannot be trusted)."""
    import drjit as dr
    return dr.select(dr.isfinite(F) & dr.isfinite(eF), _sign_of(F - eF, F + eF), 2)


def _down(v):
    """One float64 rounding of a sum, covered outward."""
    import drjit as dr
    return v - (dr.abs(v) * 2.0**-51 + 2.0**-1020)


def _up(v):
    import drjit as dr
    return v + (dr.abs(v) * 2.0**-51 + 2.0**-1020)


def _newton(t, F, g, t_lo, t_hi):
    import drjit as dr
    tn = t - F / g
    return dr.select((tn > t_lo) & (tn < t_hi), tn, 0.5 * (t_lo + t_hi))


def _first_guess(t, F, g, c2, t_lo, t_hi):
    """Where refinement starts in a new bracket: the root nearest t of the
    quadratic F + g s + c2 s^2 (F's quadratic form about t, with F's point
    value), where it lies in the bracket; else Newton's step from t."""
    import drjit as dr
    disc = g * g - 4.0 * c2 * F
    den = g + dr.select(g >= 0, 1.0, -1.0) * dr.sqrt(dr.maximum(disc, 0.0))
    tq = t - 2.0 * F / den
    ok = (disc >= 0) & (den != 0) & (tq > t_lo) & (tq < t_hi)
    return dr.select(ok, tq, _newton(t, F, g, t_lo, t_hi))


def _prepare_rays(K, o, d, t_min, t_max, active, n):
    """Checked rays, clipped to the box in float64 and moved to its entry:
    (active, t_start, _Rays)."""
    import drjit as dr
    Float, Float64 = K.m.Float, K.m64.Float
    Bool = dr.mask_t(Float)
    o64 = [Float64(o[i]) for i in range(3)]
    d64 = [Float64(d[i]) for i in range(3)]
    ok_dir = dr.isfinite(d64[0]) & dr.isfinite(d64[1]) & dr.isfinite(d64[2]) \
        & (d64[0] * d64[0] + d64[1] * d64[1] + d64[2] * d64[2] > 0) \
        & ~(dr.isnan(o64[0]) | dr.isnan(o64[1]) | dr.isnan(o64[2]))
    t_start, t_end = gridmod.clip_to_box(o64, d64, K.lo, K.hi, Float64(t_min), Float64(t_max))
    active = (Bool(active) | dr.zeros(Bool, n)) & ok_dir & (t_start <= t_end) \
        & dr.isfinite(t_start) & dr.isfinite(t_end)
    entering = active & (t_start > Float64(t_min))
    t_start = dr.select(active, t_start, 0.0)
    e64 = [dr.select(active, o64[i] - K.centre[i] + t_start * d64[i], 0.0) for i in range(3)]
    d32 = [Float(dr.select(active, d[i], 0.0)) for i in range(3)]
    dlen = dr.sqrt(d32[0] * d32[0] + d32[1] * d32[1] + d32[2] * d32[2])
    dlen = dr.select(dlen > 0, dlen, 1.0)
    cell = dr.minimum(dr.minimum(K.grid.cell[0], K.grid.cell[1]), K.grid.cell[2])
    rays = _Rays(
        e64=e64, d64=d64, e32=[Float(v) for v in e64], d32=d32,
        g_org=[Float(e64[i] + K.grid_origin[i]) for i in range(3)],
        span=Float(dr.select(active, t_end - t_start, 0.0)),
        margin=1e-3 * cell / dlen,
        cell_len=cell / dlen,
        r_min=1e-6 * K.diag / dlen,
        tol=Float64(1e-6 * K.diag / dlen),
        entering=entering)
    return active, t_start, rays


def _search(surf: Surface, o, d, t_min, t_max, active, any_hit) -> RayResult:
    with exact_arithmetic(type(o.x)):        # IEEE division and sqrt on CUDA too
        return _search_traced(surf, o, d, t_min, t_max, active, any_hit)


def _search_traced(surf: Surface, o, d, t_min, t_max, active, any_hit) -> RayResult:
    import drjit as dr
    Float = type(o.x)
    K = surf._kernel_data(Float)
    n = max(dr.width(o), dr.width(d))
    active, t_start, rays = _prepare_rays(K, o, d, t_min, t_max, active, n)
    ev = _Evaluator(surf, K, rays)
    max_it = surf.max_iterations

    walker, lane = _enter(ev, active, any_hit)
    lane = _locate(ev, walker, lane, any_hit, max_it)
    if not any_hit:
        lane = _refine(ev, lane, max_it)
    capped = lane.outcome == CAPPED
    hit = lane.outcome == HIT
    t64 = dr.select(hit, t_start + lane.t, math.inf)
    return RayResult(Float(t64), hit, lane.evals, lane.iters, capped, lane.unres & hit, t64)


#: Bezier-clipping steps (from both ends) before the walk, for a
#: polynomial f. Measured: one pays on every kind of ray (polynomial
#: surfaces 1.0-1.23x, torus shadow rays 1.97x; chmutov6 camera 0.95x);
#: two or three help incoherent rays and cost shadow and camera rays more.
POLY_CLIP_STEPS = 1

# What a lane does in one iteration of the search loop (``_Lane.mode``).
SEEK, SEARCH, TINY_A, TINY_B, EDGE, END = range(6)


@dataclass
class _Lane:
    """A ray's search state (Dr.Jit arrays, one entry per ray)."""
    mode: object         # Int32: SEEK, SEARCH, TINY_A, TINY_B, EDGE or END
    outcome: object      # Int32: WALKING, NONE, BRACKET, HIT or CAPPED
    s_cur: object        # Float: where the walk goes on from (the cell's exit)
    a: object            # Float: the cell's segment [a, b]
    b: object
    level: object        # Int32: the interval of the bisection in [a, b]
    idx: object          # Int32
    t: object            # Float64: the hit; the next point (tiny, edge, refine)
    t_lo: object         # Float64: a bracket [t_lo, t_hi] (or a tiny interval)
    t_hi: object
    s_lo: object         # Int32: sign of F at t_lo
    F_a: object          # Int32: sign of F at a tiny interval's left end;
                         # the defined end of an edge search (+1 left, -1 right)
    g_min: object        # Float64: min |g| over the bracket (0: unknown)
    bounded: object      # Bool: F bounded over the tiny interval
    unres: object        # Bool: decided at the minimum width
    evals: object        # UInt32
    iters: object        # UInt32
    rng: tuple           # the rows of the cell (table forms)

    def astuple(self):
        return tuple(getattr(self, f.name) for f in fields(self))

    @classmethod
    def start(cls, ev, active):
        import drjit as dr
        K = ev.K
        Float, Float64 = K.m.Float, K.m64.Float
        Int32, UInt32, Bool = (dr.int32_array_t(Float), dr.uint32_array_t(Float),
                               dr.mask_t(Float))
        n = dr.width(ev.rays.span)

        def z(T):
            return dr.zeros(T, n)
        return cls(dr.select(active, SEEK, END) + z(Int32), dr.select(active, WALKING, NONE)
                   + z(Int32), z(Float), z(Float), z(Float), z(Int32), z(Int32), z(Float64),
                   z(Float64), z(Float64), z(Int32), z(Int32), z(Float64), z(Bool), z(Bool),
                   z(UInt32), z(UInt32),
                   tuple((z(UInt32), z(UInt32)) for _ in (K.tables.groups if ev.tabled else ())))


def _enter(ev: _Evaluator, active, any_hit):
    """The rays' start: a clip (a quadric's, :func:`_clip_quadric`, or a
    polynomial's, :func:`_clip_polynomial`) and the first :func:`_walk`.
    Returns (walker, lane); lanes whose mode is not END go on to
    :func:`_locate`."""
    walker = gridmod.Walker(ev.K.grid, ev.rays.g_org, ev.rays.d32, ev.rays.span,
                            rows_up=ev.K.tables.up if ev.tabled else None,
                            entering=ev.rays.entering)
    lane = _Lane.start(ev, active)
    # Clip, then the first walk before the loop: a ray that meets no
    # occupied cell ends there, and a packet of such rays never runs the
    # loop's body. (Not after a quadric's clip, which settles most rays:
    # the sphere was 0.88x with it.)
    if ev.mode == "interval" and ev.surf.quadric:
        _clip_quadric(ev, lane, active, any_hit)
    else:
        if ev.poly is not None and POLY_CLIP_STEPS > 0:
            _clip_polynomial(ev, lane, active)
        _walk(ev, walker, lane)
    return walker, lane


def _locate(ev: _Evaluator, walker, lane: _Lane, any_hit, max_it) -> _Lane:
    """The loop over the occupied cells a ray crosses, nearest first, after
    :func:`_enter`. One iteration: :func:`_walk` to the next cell where a
    lane needs one, one evaluation (the interval test of the current
    interval, or a point), and :func:`_step`, the search's decision. Ends
    with a hit, a bracket to refine, no root or the cap."""
    import drjit as dr

    def body(*state):
        lane = _Lane(*state)
        _walk(ev, walker, lane)
        _step(ev, lane, any_hit, max_it)
        return lane.astuple()
    out = dr.while_loop(state=lane.astuple(),
                        cond=lambda mode, *_: mode != END, body=body, label="lgshape_search")
    return _Lane(*out)


def _clip_quadric(ev: _Evaluator, lane: _Lane, active, any_hit):
    """Clip, for a quadric (f of degree <= 2), before any walk: F's
    quadratic form over the whole ray is exact (to rounding). Where it
    excludes a root, no root; where it brackets the first root, refinement
    (for an any-hit query, a hit); else the walk starts where the first
    root may be (:meth:`_Evaluator.clip`)."""
    import drjit as dr
    free, first, crossed, b_lo, b_hi, s_lo = ev.clip(
        dr.zeros(ev.K.m.Float, dr.width(ev.rays.span)), ev.rays.span, active)
    lane.s_cur = first
    lane.mode = dr.select(free | crossed, END, lane.mode)
    lane.outcome = dr.select(free, NONE, dr.select(crossed, HIT if any_hit else BRACKET,
                                                   lane.outcome))
    lane.t_lo = dr.select(crossed, b_lo, lane.t_lo)
    lane.t_hi = dr.select(crossed, b_hi, lane.t_hi)
    lane.s_lo = dr.select(crossed, s_lo, lane.s_lo)
    lane.t = dr.select(crossed, 0.5 * (b_lo + b_hi), lane.t)
    lane.evals = lane.evals + dr.select(active, 1, 0)


def _clip_polynomial(ev: _Evaluator, lane: _Lane, active):
    """Clip, for a polynomial f (the ray's coefficients), before any walk:
    the convex hulls of F's Bernstein coefficients prove that no root lies
    before ``first`` on the ray, or none at all
    (:func:`lgshape.expr.raypoly.clip_first_root`); the walk starts there.
    Rays that miss the surface, most of a camera's rays in the box, end
    here without walking the empty cells."""
    import drjit as dr
    Float = ev.K.m.Float
    c, w = ev.poly
    m64 = ev.K.m64

    def clip(span):           # (a branch: packets of rays that miss the box skip it)
        return raypoly.clip_first_root(m64, c, w, span, steps=POLY_CLIP_STEPS)
    free, first = dr.if_stmt(args=(m64.Float(ev.rays.span),), cond=active, true_fn=clip,
                             false_fn=lambda span: (dr.mask_t(span)(False), span),
                             label="lgshape_poly_clip")
    first = Float(first)
    first = dr.maximum(first - dr.abs(first) * 2.0**-22, 0.0)    # float32, rounded down
    free = active & free
    lane.s_cur = dr.select(active, first, lane.s_cur)
    lane.mode = dr.select(free, END, lane.mode)
    lane.outcome = dr.select(free, NONE, lane.outcome)
    lane.evals = lane.evals + dr.select(active, 1, 0)


def _walk(ev: _Evaluator, walker, lane: _Lane):
    """Walk: lanes in SEEK go to the next occupied cell (the DDA of
    :class:`lgshape.grid.Walker`); its segment (over SPAN_CELLS cells where
    the search takes spans), widened by the margin, becomes the root of the
    bisection; no cell left: no root."""
    import drjit as dr
    R = ev.rays
    seek = lane.mode == SEEK
    found, ta, tb, stuck, slot = walker.next(lane.s_cur, seek)
    if ev.mode == "interval" and not ev.tabled:
        tb = dr.maximum(tb, ta + SPAN_CELLS * R.cell_len)
    if ev.tabled:       # the cell's rows
        new = ev.K.tables.ranges(slot, seek & found)
        lane.rng = tuple((dr.select(seek, ns, s_), dr.select(seek, ne, e_))
                         for (ns, ne), (s_, e_) in zip(new, lane.rng))
    a = dr.maximum(ta - R.margin, 0.0)
    b = dr.minimum(tb + R.margin, R.span)
    lane.s_cur = dr.select(seek, tb, lane.s_cur)
    lane.a = dr.select(seek, a, lane.a)
    lane.b = dr.select(seek, b, lane.b)
    lane.level = dr.select(seek, 0, lane.level)
    lane.idx = dr.select(seek, 0, lane.idx)
    cell = found & (a <= b)
    lane.outcome = dr.select(seek & stuck, CAPPED,            # a walk that cannot end
                   dr.select(seek & ~cell, NONE, lane.outcome))
    lane.mode = dr.select(seek, dr.select(cell, SEARCH, END), lane.mode)


def _step(ev: _Evaluator, lane: _Lane, any_hit, max_it):
    """Search: one evaluation and the decision it allows. A SEARCH lane
    tests its interval of the bisection (the whole cell first): no root ->
    the next interval (the next cell after the last); one root -> a bracket
    (to refine); undecided -> split, or, below the minimum width, the rare
    cases of :func:`_small` (tiny intervals, edges of f's domain), in a
    branch that a SIMD packet runs only where one of its lanes needs it."""
    import drjit as dr
    R = ev.rays
    Float64 = ev.K.m64.Float
    UInt32 = dr.uint32_array_t(ev.K.m.Float)
    mode = lane.mode
    searching = mode == SEARCH
    lo, hi = _interval_of(lane.level, lane.idx, lane.a, lane.b)
    tm = 0.5 * (Float64(lo) + Float64(hi))
    # the point: at the middle of a SEARCH lane's interval, or where a
    # rare case looks (_small)
    want = searching | (mode == TINY_A) | (mode == TINY_B) | (mode == EDGE)
    P, B, c2 = ev.point_and_bounds(dr.select(searching, tm, lane.t), lo, hi, lane.rng,
                                   searching & (ev.mode != "global"), want)
    F, eF, g, eg, _ = P
    T = ev.test(lo, hi, lane.rng, searching, P, B)
    busy = mode != END
    lane.iters = lane.iters + dr.select(busy, 1, 0)
    lane.evals = lane.evals + dr.select(busy, 1, 0) + dr.select(searching, UInt32(T.evals - 1), 0)

    # ---- no root: the next interval; one root: a bracket; else split ----
    # (an any-hit query stops at any proven root: a sign change will do)
    cross = T.crossing & ~T.bracket & any_hit
    tiny = T.open & ~cross & ((T.r < R.r_min) | (lane.level >= MAX_LEVEL))
    split = T.open & ~cross & ~tiny
    lv_n, ix_n, seg_done = _advance(lane.level, lane.idx)
    lane.level = dr.select(split, lane.level + 1, dr.select(T.empty, lv_n, lane.level))
    lane.idx = dr.select(split, lane.idx << 1, dr.select(T.empty, ix_n, lane.idx))
    br = T.bracket
    lane.t_lo = dr.select(br, T.b_lo, lane.t_lo)
    lane.t_hi = dr.select(br, T.b_hi, lane.t_hi)
    lane.s_lo = dr.select(br, T.b_sign, lane.s_lo)
    lane.g_min = dr.select(br, T.g_min, lane.g_min)
    if any_hit:          # a bracket proves a root: enough for an any-hit query
        lane.t = dr.select(br, 0.5 * (T.b_lo + T.b_hi), dr.select(cross, tm, lane.t))
        br = br | cross
        lane.outcome = dr.select(br, HIT, lane.outcome)
    else:
        lane.t = dr.select(br, _first_guess(tm, F, g, c2, T.b_lo, T.b_hi), lane.t)
        lane.outcome = dr.select(br, BRACKET, lane.outcome)
    lane.mode = dr.select(br, END, dr.select(T.empty & seg_done, SEEK, mode))

    # ---- the rare cases ----
    rare = tiny | (mode == TINY_A) | (mode == TINY_B) | (mode == EDGE)

    def small(*args):
        ln = _Lane(*args[:-10])
        _small(ev, ln, *args[-10:], any_hit)
        return ln.astuple()
    state = dr.if_stmt(args=lane.astuple() + (mode, tiny, F, eF, tm, lo, hi, T.defined & T.bounded
                                              & (T.s_m == 0), T.bounded, T.g_min),
                       cond=rare, true_fn=small, false_fn=lambda *args: args[:-10],
                       label="lgshape_small")
    for f, v in zip(fields(lane), state):
        setattr(lane, f.name, v)
    capped = (lane.mode != END) & (lane.iters >= max_it)
    lane.outcome = dr.select(capped, CAPPED, lane.outcome)
    lane.mode = dr.select(capped, END, lane.mode)


def _small(ev: _Evaluator, lane: _Lane, mode, tiny, F, eF, tm, lo, hi, zero_mid, bounded,
           g_min, any_hit):
    """Intervals below the minimum width, and the edges of f's domain.

    A tiny interval (``tiny``) whose middle value is within its error bound
    of 0 (``zero_mid``) is a hit: a tangent touch or singular point, to float
    precision. Else F at both its ends decides (TINY_A, TINY_B: one point
    each); a bracket found so is resolved where g keeps one sign on the
    interval. Where one end lies outside f's domain, the root may lie between
    the domain's edge and the defined end: found by bisecting towards the
    edge, watching the sign (EDGE)."""
    import drjit as dr
    R = ev.rays
    Float64 = ev.K.m64.Float
    tiny_zero = tiny & zero_mid
    tiny_check = tiny & ~tiny_zero

    # ---- tiny interval: F at both ends decides (two iterations) ----
    tiny_a, tiny_b = mode == TINY_A, mode == TINY_B
    s_here = _sign_known(F, eF)
    s1, s2 = lane.F_a, s_here              # F_a holds the sign at the left end
    ends_ok = tiny_b & lane.bounded & (s1 != 2) & (s2 != 2)
    tiny_root = ends_ok & (s1 != s2)
    # one end outside f's domain: the root may lie between the domain's
    # edge and the defined end; the edge search looks there
    one_end = tiny_b & lane.bounded & ((s1 == 2) != (s2 == 2))
    s_def = dr.select(s1 == 2, s2, s1)
    edge_at_end = one_end & (s_def == 0)
    tiny_at_end = (tiny_root & ((s1 == 0) | (s2 == 0))) | edge_at_end
    tiny_bracket = tiny_root & ~tiny_at_end
    edge_start = one_end & ~edge_at_end
    tiny_none = tiny_b & ~tiny_root & ~one_end

    # ---- edge of the domain: bisect towards it ----
    # [t_lo, t_hi] has one defined end (F_a: +1 the left one, -1 the right
    # one) of sign s_lo; each step looks at the middle t.
    t_lo, t_hi, t_n = lane.t_lo, lane.t_hi, lane.t
    edge = mode == EDGE
    left_def = lane.F_a > 0
    edge_zero = edge & (s_here == 0)
    edge_bracket = edge & (s_here != 2) & (s_here != 0) & (s_here != lane.s_lo)
    undef_to_mid = edge & (s_here == 2)
    def_to_mid = edge & (s_here == lane.s_lo)
    e_lo = dr.select((undef_to_mid & ~left_def) | (def_to_mid & left_def), t_n, t_lo)
    e_hi = dr.select((undef_to_mid & left_def) | (def_to_mid & ~left_def), t_n, t_hi)
    edge_none = (undef_to_mid | def_to_mid) & ((e_hi - e_lo < 1e-4 * R.tol)
                                               | (t_n <= t_lo) | (t_n >= t_hi))

    # ---- transitions ----
    lv_n, ix_n, seg_done = _advance(lane.level, lane.idx)
    moving_on = tiny_none | edge_none
    lane.level = dr.select(moving_on, lv_n, lane.level)
    lane.idx = dr.select(moving_on, ix_n, lane.idx)
    # an edge bracket lies between the middle and the defined end
    eb_lo, eb_hi = dr.select(left_def, t_lo, t_n), dr.select(left_def, t_n, t_hi)
    t_lo = dr.select(tiny_check, Float64(lo),
           dr.select(edge_bracket, eb_lo, dr.select(edge, e_lo, t_lo)))
    t_hi = dr.select(tiny_check, Float64(hi),
           dr.select(edge_bracket, eb_hi, dr.select(edge, e_hi, t_hi)))
    lane.s_lo = dr.select(tiny_bracket, s1, dr.select(edge_start, s_def,
                dr.select(edge_bracket & ~left_def, s_here, lane.s_lo)))
    new_bracket = tiny_bracket | edge_bracket
    # a tiny bracket where g keeps one sign (``g_min``, kept from the tiny
    # interval's test) is a bracket as the test's are: one simple root, its
    # ends' signs from point values where the test's bounds could not tell
    # them (a root within rounding of a float32 end of the bisection)
    mono_bracket = tiny_bracket & (lane.g_min > 0)
    lane.g_min = dr.select(new_bracket & ~mono_bracket, 0.0,
                           dr.select(tiny_check, g_min, lane.g_min))
    lane.bounded = dr.select(tiny_check, bounded, lane.bounded)
    lane.F_a = dr.select(tiny_a, s_here,
               dr.select(edge_start, dr.select(s1 == 2, -1, 1), lane.F_a))
    found = tiny_zero | edge_zero | tiny_at_end
    at_end = dr.select(s1 == 0, t_lo, t_hi)      # (the tiny interval's ends)
    lane.t = dr.select(tiny_check, t_lo, dr.select(tiny_a, t_hi,
             dr.select(new_bracket | edge_start | edge, 0.5 * (t_lo + t_hi),
             dr.select(tiny_zero, tm, dr.select(tiny_at_end, at_end, t_n)))))
    lane.t_lo, lane.t_hi = t_lo, t_hi
    # a bracket found here is unresolved too (decided at the minimum width),
    # unless g keeps one sign there
    lane.unres = lane.unres | found | (new_bracket & ~mono_bracket & (not any_hit))
    if any_hit:
        lane.t = dr.select(new_bracket, 0.5 * (t_lo + t_hi), lane.t)
        found = found | new_bracket
    lane.outcome = dr.select(found, HIT, dr.select(new_bracket, BRACKET, lane.outcome))
    lane.mode = dr.select(found | new_bracket, END,
                dr.select(tiny_check, TINY_A, dr.select(tiny_a, TINY_B,
                dr.select(edge_start, EDGE,
                dr.select(moving_on, dr.select(seg_done, SEEK, SEARCH),
                dr.select(tiny_b, SEARCH, lane.mode))))))


def _interval_of(level, idx, a, b):
    """The idx-th of the 2^level equal parts of [a, b] (the last one ends
    at b exactly)."""
    import drjit as dr
    Float = type(a)
    UInt32, Int32 = dr.uint32_array_t(Float), dr.int32_array_t(Float)
    w = (b - a) / Float(UInt32(1) << UInt32(level))
    last = idx + 1 == (Int32(1) << level)
    return a + Float(idx) * w, dr.select(last, b, a + Float(idx + 1) * w)


def _advance(level, idx):
    """The next interval to the right in the implicit binary tree, and
    whether the tree is done."""
    import drjit as dr
    nxt = idx + 1
    tz = dr.minimum(type(idx)(dr.tzcnt(dr.uint32_array_t(type(idx))(nxt))), level)
    level, idx = level - tz, nxt >> tz
    return level, idx, (level == 0) & (idx == 1)


def _refine(ev: _Evaluator, lane: _Lane, max_it) -> _Lane:
    """Refine: safeguarded Newton in float64 in each bracket (bisection
    where a step leaves it) until the step, the bracket, or the proven
    distance to the root |F| / min |g|, is below the tolerance. A loop of
    its own after the search, with only its own state."""
    import drjit as dr
    R = ev.rays

    def body(outcome, t, t_lo, t_hi, evals, iters):
        refining = outcome == BRACKET
        F, g = ev.steer(t, lane.rng)
        same = dr.select(F > 0, 1, dr.select(F < 0, -1, 0)) == lane.s_lo
        r_lo = dr.select(refining & same, t, t_lo)
        r_hi = dr.select(refining & ~same, t, t_hi)
        t_next = _newton(t, F, g, r_lo, r_hi)
        # where |F| / min |g| on the bracket (a proven distance to the root)
        # is below tol, t is within tol already: take its Newton step kept
        # in the bracket, never the safeguard's bisection midpoint
        close = (F == 0) | (dr.abs(F) < lane.g_min * R.tol)
        t_next = dr.select(F == 0, t, dr.select(close, dr.clip(t - F / g, r_lo, r_hi), t_next))
        conv = refining & (close | (dr.abs(t_next - t) < R.tol) | (r_hi - r_lo < R.tol))
        iters = iters + dr.select(refining, 1, 0)
        evals = evals + dr.select(refining, 1, 0)
        outcome = dr.select(conv, HIT,
                  dr.select(refining & (iters >= max_it), CAPPED, outcome))
        return outcome, dr.select(refining, t_next, t), r_lo, r_hi, evals, iters

    out = dr.while_loop(state=(lane.outcome, lane.t, lane.t_lo, lane.t_hi, lane.evals,
                               lane.iters),
                        cond=lambda outcome, *_: outcome == BRACKET, body=body,
                        label="lgshape_refine")
    lane.outcome, lane.t, lane.t_lo, lane.t_hi, lane.evals, lane.iters = out
    return lane
