"""Guaranteed ray queries on an implicit surface f = 0: :class:`Surface`,
its checks, its inputs and its frozen queries.

A Surface holds f (an expression, a library surface or a table form of
many primitives), its box, the pruning grid (:mod:`lgshape.grid`) and the
compiled search's constants. :meth:`Surface.trace` checks and converts the
rays and runs the search (:mod:`lgshape.search`: the walk, the bisection,
the refinement), whose evaluator (:mod:`lgshape.evaluator`) bounds F(t) =
f(o + t d) and its slope along each ray.

**The contract for the roots of any f.** Where f is NaN or infinite there
is no surface. A root is reported only where F is continuous and crosses
zero, or is proven to touch it (|F| within its rounding error bound of 0):

- a sign change across a pole (where the interval of F over the smallest
  interval is unbounded) is not a root;
- a sign change across a gap where f is undefined is not a root (the
  derivative is unbounded at the edge of a domain, so the monotonicity test
  never spans the gap, and the ends must both be defined); where one end of
  a smallest interval is undefined, a root between the domain's edge and
  the defined end is looked for by bisecting towards it;
- an f that is NaN or infinite at every sampled point of its box is refused
  at construction (:class:`Surface`).

The first root in [t_min, t_max] is found (to 1e-6 of the box diagonal),
whatever t_max beyond it; tangent touches (roots of even multiplicity) may
be reported or not, and a hit decided at the minimum width is flagged
``unresolved``. Signs are decided only outside the rounding error bounds of
float64 point values, so the hits of k * f are those of f; geometry far from
the origin is solved in coordinates local to the box, to the same relative
accuracy as near it. The returned t is float32 (as Mitsuba's), so it carries
its own rounding, ulp(t) / 2; :attr:`RayResult.t64` keeps the float64 value.

**Every ray ends.** Rays with a zero, infinite or NaN direction, or a NaN
origin, are misses; a ray that reaches ``max_iterations`` is counted in
``capped`` and reported as a miss, never silently (the benchmark counts
capped rays as defects).

Everything on the device is Dr.Jit code without host round trips: it runs
in LLVM and CUDA and inside Mitsuba integrators. Constants are opaque, so
another Surface of the same expression shape reuses the compiled kernels.
"""
from __future__ import annotations

import contextlib
import gc
import math
import numbers
import sys
import warnings

import drjit as dr
import numpy as np

from . import bounds, grid as gridmod
from . import tables as tablemod
from .arraymath import NUMPY, DrJitMath
from .evaluator import KernelData, table_point
from .expr import (Expr, evaluate, gradient, hessian, parse, ray_derivatives, raypoly,
                   raytrig)
from .expr.horner import horner
from .expr.node import constant_value, topological
from .expr.shift import localize
from .search import RayResult, empty_result, search
from .surfaces import Implicit
from .tables import DeviceTables, TableForm, evaluate_points, find_tables

__all__ = ["DEFAULT_DEPTH", "EmptySurfaceWarning", "FREEZE_LIMIT", "MAX_FUSED_NODES",
           "MAX_NODES", "SEARCH_MODES", "RayResult", "Surface", "call_frozen", "check_rays",
           "default_array3f"]

#: How an interval of the ray is bounded: ``"interval"`` (g = dF/dt over the
#: interval by interval arithmetic, the mean-value form), ``"taylor"`` (the
#: seed's test with a local G >= |d^T H d| per interval) and ``"global"`` (the
#: seed's test with one G: hand-given, or the Hessian norm over the box).
SEARCH_MODES = ("interval", "taylor", "global")

#: Points sampled to check hand-given L and G, and that f is defined somewhere.
CHECK_SAMPLES = 4096

#: The expression path takes f with its sums of powers of a common
#: subexpression in Horner form (:mod:`lgshape.expr.horner`); False: f as
#: written (for comparison, docs/kernel-plan.md).
HORNER = True

#: Recordings kept per frozen query (one per ray count and argument layout;
#: least recently used dropped), see :meth:`Surface.trace`.
FREEZE_LIMIT = 8

#: The most nodes (shared subexpressions once) of a plain expression: a
#: larger one is refused (ValueError naming both numbers). The construction's
#: passes over f (tables, derivatives, coordinates) are linear in its size.
MAX_NODES = 200_000

#: The most nodes of an expression evaluated whole in the search's kernel
#: (no table found in it, or ``tables=False``, L, G or another search mode):
#: a larger one is refused. Dr.Jit's compiler is not linear in a kernel's
#: size (minutes for tens of thousands of nodes; a chain 10,000 deep
#: overflows its stack), and the kernel holds f, its ray derivatives and
#: their interval forms.
MAX_FUSED_NODES = 20_000


class EmptySurfaceWarning(UserWarning):
    """A Surface whose f has no zero in its box (its pruning grid has no
    cells: a nonzero constant f, or a surface outside the box): every ray
    misses. Warned once, when the Surface is built."""


def _shown(f, limit: int = 200) -> str:
    """f as messages quote it: a long expression is cut."""
    text = repr(f)
    return text if len(text) <= limit else f"{text[:limit - 40]} ... {text[-30:]}"


def _check_size(f, limit, what):
    n = f.size()
    if n > limit:
        name = "MAX_NODES" if limit == MAX_NODES else "MAX_FUSED_NODES"
        raise ValueError(f"f has {n} nodes, over the limit of {limit} for {what} "
                         f"(lgshape.trace.{name})")


def _check_not_zero(f):
    """Refuse an f that is 0 everywhere (every point is on the surface, which
    has no normal): a constant 0 once its named constants take their values.
    A nonzero constant has no surface: built, and warned of as empty."""
    if constant_value(f) == 0.0:
        raise ValueError(f"f = {_shown(f)} is identically 0 (with its named constants' values): "
                         f"every point of the box would be on the surface; an implicit "
                         f"surface needs an f that changes sign")


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
#: gigabytes). docs/kernel-plan.md gives the measurements behind both.
DEFAULT_DEPTH = 7
DEEP_MAX_NODES = 128


def _default_depth(tables, f=None) -> int:
    """:data:`DEFAULT_DEPTH` for a plain expression f of at most
    :data:`DEEP_MAX_NODES` nodes, else 6; for a table form, 6 and finer
    with more rows (7 from 300 rows, 8 from 3000), which keeps about one row
    per cell where primitives are dense (the benchmark's scale section)."""
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
    the cells are cubes: the walk's empty boxes are counted in cells, and a
    ray crosses a flat cell's short edge in a short step. Near-cubic boxes
    keep their cells: there the longer spans of cubic cells cost the search
    more than the walk gains (docs/kernel-plan.md). Rays are clipped to [lo, hi]
    all the same; cells outside it are never walked."""
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
    surface anywhere: that is refused with a ValueError; so is an f that is
    identically 0 (a constant 0 once its named constants take their values:
    every point would be on it). A nonzero constant f (or any f without a
    zero in the box) builds with no cells, warns once
    (:class:`EmptySurfaceWarning`), and every ray misses. A plain expression
    over :data:`MAX_NODES` nodes, or one evaluated whole in the kernel over
    :data:`MAX_FUSED_NODES`, is refused with a ValueError naming the limit.

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
        if not isinstance(f, TableForm):
            _check_size(f, MAX_NODES, "an expression")
            _check_not_zero(f)
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
            _check_size(self.local_expr, MAX_FUSED_NODES,
                        "an expression evaluated whole in the search's kernel (a sum, min or "
                        f"max of at least {tablemod.MIN_ROWS} parts of one structure is "
                        "evaluated per cell instead)")
            self.g_expr, self.h_expr = ray_derivatives(self.local_expr)
            #: f is defined and finite wherever its interval forms are
            #: finite (no division by a variable, sqrt, log or negative
            #: power), so those forms alone may prove g's sign and F's at
            #: an interval's ends (:meth:`lgshape.evaluator.Evaluator._decided`)
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
        if len(self.grid.cells) == 0:
            shown = self.tables if self.tables is not None else self.expr
            warnings.warn(EmptySurfaceWarning(
                f"f = {_shown(shown)} has no zero in the box {self.bbox} (its pruning grid has "
                f"no cells): every ray misses"), stacklevel=2)
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
            Float64 = dr.float64_array_t(Float)
            dev = gridmod.DeviceGrid(self.grid, Float)
            self._device[key] = KernelData(
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
            _, _, g = table_point(K, p, with_gradient=True)
            return type(p)(*(Float(v) for v in g))
        # (0 / 0 in a distance's slope read as 0: tables.point_slope)
        gx, gy, gz = evaluate([tablemod.point_slope(g) for g in gradient(self.expr)],
                              {"x": p.x, "y": p.y, "z": p.z}, K.m)
        zero = dr.zeros(Float, dr.width(p))     # a constant component: one per point
        return type(p)(gx + zero, gy + zero, gz + zero)

    def normal(self, p):
        """The unit normal grad f / |grad f| (towards f > 0)."""
        g = self.gradient(p)
        n2 = dr.squared_norm(g)
        return dr.select(n2 > 0, g * dr.rsqrt(n2), type(g)(0, 0, 1))

    def value(self, p):
        """f at points p."""
        p = _points(p)
        K = self._kernel_data(type(p.x))
        if K.tables is not None:
            return type(p.x)(table_point(K, p)[0])
        Float = type(p.x)                        # a constant f: one value per point
        return Float(evaluate(self.expr, {"x": p.x, "y": p.y, "z": p.z}, K.m)) \
            + dr.zeros(Float, dr.width(p))

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
        o, d, n = check_rays(o, d, t_min, t_max, active)
        if n == 0:
            return empty_result(type(o.x))
        if self.freeze and _freezable(o, d, t_min, t_max, active):
            return call_frozen(self._frozen_search(any_hit),
                               self._kernel_data(type(o.x)), o, d, t_min, t_max, active, n)
        return search(self, o, d, t_min, t_max, active, any_hit)

    def _frozen_search(self, any_hit):
        """The search as a frozen function, one per query kind. Its inputs:
        the kernel data (so that the grid, the tables and the opaque
        constants are read on every launch), the rays, and the ray count
        (recorded kernels are sized by it); one per setting of
        ``ray_polynomial`` too (the recording holds the path it took)."""
        key = (any_hit, self.ray_polynomial)
        fn = self._frozen.get(key)
        if fn is None:

            def frozen(K, o, d, t_min, t_max, active, n):
                return search(self, o, d, t_min, t_max, active, any_hit)
            fn = self._frozen[key] = dr.freeze(frozen, limit=FREEZE_LIMIT, warn_after=2**30)
        return fn



# ---------------------------------------------------------------------------
# Inputs
# ---------------------------------------------------------------------------

def _width(v):
    if isinstance(v, np.ndarray):
        return v.size if v.ndim else 1
    return dr.width(v) if dr.is_array_v(v) else 1


def _points(p):
    """Points as a Dr.Jit Array3f (numpy input: (N, 3) or (3,))."""
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
    # (the backend's module imported where it is chosen)
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


def check_rays(o, d, t_min, t_max, active):
    """Checked ray arrays: (o, d, n) with o, d Dr.Jit Array3f."""
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
    if not dr.is_jit_v(o) or dr.grad_enabled(o, d) or dr.flag(dr.JitFlag.SymbolicScope):
        return False
    return all(dr.is_array_v(v) or isinstance(v, (bool, numbers.Real))
               for v in (t_min, t_max, active))


@contextlib.contextmanager
def collection_paused():
    """Python's cyclic garbage collector paused within it (restored after).

    Dr.Jit 1.5 keys the callables of a virtual call traced into a kernel by
    their code and by whether the call has one instance or several, but names
    them by their code alone. A vcall over Mitsuba's shapes has one instance
    per shape alive in the process, so when the collector frees an earlier
    scene's shapes between two vcalls traced into one kernel (one call sees
    two shapes, the next one), the kernel defines one function twice and
    LLVM refuses it: the process aborts ("invalid redefinition of function").
    The lg integrators' renders and gradient passes run within it (their
    entry points are decorated with it); the collector runs again after
    them."""
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


def call_frozen(fn, *args):
    """fn(*args) for a frozen function, with Python's cyclic garbage
    collector paused (:func:`collection_paused`): a collection while it
    records could also free arrays that map host memory, which Dr.Jit 1.5
    does not allow then (it aborts the process)."""
    with collection_paused():
        return fn(*args)

