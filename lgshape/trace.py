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

The bounds come from one of :data:`SEARCH_MODES`: ``"interval"`` bounds g
over the interval by interval arithmetic (F in F(t_m) + [g] [-r, r]);
``"taylor"`` and ``"global"`` are the seed's test |g(t_m)| > G r with G >= |h|
local to the interval or global (plus F in F(t_m) +- |g(t_m)| r + [h] r^2/2).

F and g at a point are evaluated in float64 and widened to a float32
enclosure by 2^-22 relative plus an absolute ``point_error`` (2^-40 times the
sum over the DAG of each node's largest magnitude over the box, from float64
interval arithmetic): the assumed bound of float64 rounding, far below what
float32 decisions resolve. So float32 noise never decides a sign.

A bracketed single root is refined by safeguarded Newton in float64
(bisection where a step leaves the bracket) until the step, or the proven
distance |F| / min |g|, is below 1e-6 of the box diagonal. Intervals are
visited left to right, so the first root found is the nearest. Below a
minimum width (1e-6 of the diagonal) an interval that cannot be excluded is a
root where F changes sign across it, or where F at its middle cannot be told
from 0 (a tangent touch or singular point, counted as ``unresolved``);
otherwise the search goes on after it. Tangent touches (roots of even
multiplicity) may therefore be reported or not. A ray that reaches the
iteration bound is counted in ``capped`` and reported as a miss of the
search, never silently.

Everything is Dr.Jit code without host round trips: it runs in LLVM and CUDA
and inside Mitsuba integrators. Constants are opaque, so another Surface of
the same expression shape reuses the compiled kernels.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from . import bounds, grid as gridmod
from .arraymath import DrJitMath
from .expr import Expr, evaluate, gradient, parse, ray_derivatives
from .interval import Interval
from .surfaces import Implicit

MAX_LEVEL = 22          # bisection depth bound inside one cell segment

#: How an interval of the ray is bounded: ``"interval"`` (g = dF/dt over the
#: interval by interval arithmetic, the mean-value form), ``"taylor"`` (the
#: seed's test with a local G >= |d^T H d| per interval) and ``"global"`` (the
#: seed's test with one G: hand-given, or the Hessian norm over the box).
SEARCH_MODES = ("interval", "taylor", "global")


@dataclass
class RayResult:
    """Per-ray output of :meth:`Surface.trace` (Dr.Jit arrays)."""
    t: object            # Float: nearest root, inf where none
    hit: object          # Bool
    evals: object        # UInt32: point + interval evaluations
    iterations: object   # UInt32: search + refinement iterations
    capped: object       # Bool: reached the iteration bound
    unresolved: object   # Bool: hit decided at the minimum width (tangent/singular)


def _as_expr(expr):
    if isinstance(expr, Implicit):
        return expr.expr, expr.bbox
    if isinstance(expr, str):
        return parse(expr), None
    if isinstance(expr, Expr):
        return expr, None
    raise TypeError(f"expected an expression, a string or a library surface, "
                    f"not {type(expr).__name__}")


def _point_error(f, lo, hi) -> float:
    from .arraymath import NUMPY
    from .expr import evaluate_interval
    from .expr.node import topological
    nodes = [n for n in topological([f]) if n.op not in ("const", "var")]
    with np.errstate(all="ignore"):
        res = evaluate_interval(nodes, bounds.box_env(lo[None], hi[None]), NUMPY)
    total = sum(float(np.max(np.maximum(np.abs(r.lo), np.abs(r.hi)))) for r in res)
    return total * 2.0**-40 if np.isfinite(total) else 0.0


class Surface:
    """An implicit surface f = 0 inside a box, ready for guaranteed ray queries.

    ``expr``: an expression, a string of the expression language or a library
    surface (:mod:`lgshape.surfaces`, which brings its own box). ``bbox``:
    ``((x0, y0, z0), (x1, y1, z1))``. ``L``: a hand-given Lipschitz constant of
    f over the box (then the pruning uses the seed's global test). ``G``: a
    hand-given bound of |d^2 F/dt^2| for unit directions (then the search uses
    it instead of local interval bounds). ``depth``: the pruning depth (2**depth
    cells per axis). ``search``: how ray intervals are bounded, see
    :data:`SEARCH_MODES` (default ``"interval"``, or ``"global"`` when ``G`` is
    given). ``max_iterations``: the per-ray bound on search steps.
    """

    def __init__(self, expr, bbox=None, *, L: float | None = None, G: float | None = None,
                 depth: int | None = None, search: str | None = None,
                 max_iterations: int = 4096):
        f, default_box = _as_expr(expr)
        bbox = bbox if bbox is not None else default_box
        if bbox is None:
            raise ValueError("Surface needs a bbox ((x0, y0, z0), (x1, y1, z1)) for a plain expression")
        lo, hi = (np.asarray(v, dtype=np.float64).reshape(3) for v in bbox)
        if not np.all(hi > lo):
            raise ValueError(f"bbox must have min < max on every axis, got {bbox}")
        for name, v in (("L", L), ("G", G)):
            if v is not None and not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive finite number, got {v}")
        self.expr, self.lo, self.hi = f, lo, hi
        self.g_expr, self.h_expr = ray_derivatives(f)
        self.L, self.G_hand = L, G
        self.depth = 6 if depth is None else int(depth)
        if search is None:
            search = "global" if G is not None else "interval"
        if search not in SEARCH_MODES:
            raise ValueError(f"unknown search mode {search!r} (one of {', '.join(SEARCH_MODES)})")
        self.search = search
        self.max_iterations = int(max_iterations)
        self.grid = gridmod.build(f, lo, hi, self.depth,
                                  mode="global" if L is not None else "local", L=L)
        self._device = {}
        # Absolute error bound of a float64 point evaluation of f in the box
        # (POINT_ERROR): 2^-40 times the sum over the DAG of each node's
        # largest magnitude over the box (float64 interval arithmetic).
        self.point_error = _point_error(f, lo, hi)

    # -- host-side facts ------------------------------------------------------
    @property
    def bbox(self):
        return tuple(map(float, self.lo)), tuple(map(float, self.hi))

    @property
    def diagonal(self) -> float:
        return float(np.linalg.norm(self.hi - self.lo))

    @property
    def memory_bytes(self) -> int:
        """Size of the pruning structure (brick map)."""
        return self.grid.nbytes

    def global_G(self) -> float:
        """G for unit directions: the hand-given one, else the Hessian norm over the box."""
        if self.G_hand is not None:
            return self.G_hand
        return float(bounds.hessian_norm(self.expr, self.lo[None], self.hi[None])[0])

    def __repr__(self):
        return (f"Surface({self.expr!r}, bbox={self.bbox}, depth={self.depth}, "
                f"cells={len(self.grid.cells)})")

    # -- Dr.Jit side ------------------------------------------------------------
    def _kernel_data(self, Float):
        key = Float
        if key not in self._device:
            import drjit as dr
            m = (DrJitMath(Float), DrJitMath(dr.float64_array_t(Float)))
            dev = gridmod.DeviceGrid(self.grid, Float)
            box = ([dr.opaque(Float, float(v)) for v in self.lo],
                   [dr.opaque(Float, float(v)) for v in self.hi])
            self._device[key] = (m, dev, dr.opaque(Float, self.point_error), box,
                                 dr.opaque(Float, self.diagonal))
        return self._device[key]

    @staticmethod
    def _arrays(o, d):
        import drjit as dr
        if not dr.is_array_v(o):
            from drjit.llvm.ad import Array3f
            o, d = (np.ascontiguousarray(np.asarray(v, dtype=np.float32).reshape(-1, 3).T) for v in (o, d))
            o, d = Array3f(o), Array3f(d)
            dr.eval(o, d)
            return o, d
        return o, d

    def gradient(self, p):
        """grad f at points p (Array3f or (N, 3) numpy)."""
        p, _ = self._arrays(p, p)
        Float = type(p.x)
        m = self._kernel_data(Float)[0][0]
        gx, gy, gz = evaluate(list(gradient(self.expr)), {"x": p.x, "y": p.y, "z": p.z}, m)
        return type(p)(gx, gy, gz)

    def normal(self, p):
        """The unit normal grad f / |grad f| (towards f > 0)."""
        import drjit as dr
        g = self.gradient(p)
        n2 = dr.squared_norm(g)
        return dr.select(n2 > 0, g * dr.rsqrt(n2), type(g)(0, 0, 1))

    def value(self, p):
        """f at points p."""
        p, _ = self._arrays(p, p)
        return evaluate(self.expr, {"x": p.x, "y": p.y, "z": p.z}, self._kernel_data(type(p.x))[0][0])

    def intersect(self, o, d, t_min=0.0, t_max=math.inf, active=True):
        """Nearest root t in [t_min, t_max] along o + t d: returns (t, hit),
        t = inf where there is none."""
        r = self.trace(o, d, t_min, t_max, active)
        return r.t, r.hit

    def occluded(self, o, d, t_max, active=True, t_min=0.0):
        """Any root in [t_min, t_max]? Stops at the first proven root."""
        return self.trace(o, d, t_min, t_max, active, any_hit=True).hit

    def trace(self, o, d, t_min=0.0, t_max=math.inf, active=True, any_hit=False) -> RayResult:
        """The search with its per-ray statistics (see :class:`RayResult`)."""
        import drjit as dr
        o, d = self._arrays(o, d)
        Float = type(o.x)
        UInt32 = dr.uint32_array_t(Float)
        Int32 = dr.int32_array_t(Float)
        Bool = dr.mask_t(Float)
        (m, m64), dev, point_err, (blo, bhi), diag = self._kernel_data(Float)
        Float64 = m64.Float
        n = max(dr.width(o), dr.width(d))
        f, ge, he = self.expr, self.g_expr, self.h_expr
        search_mode = self.search
        if search_mode == "global":
            G_glob = dr.opaque(Float, self.global_G()) * dr.squared_norm(d)

        t_start, t_end = gridmod.clip_to_box(o, d, blo, bhi, t_min, t_max)
        active = (Bool(active) | dr.zeros(Bool, n)) & (t_start <= t_end) & dr.isfinite(t_start)

        dlen = dr.norm(d)
        cell = dr.minimum(dr.minimum(dev.cell[0], dev.cell[1]), dev.cell[2])
        margin = 1e-3 * cell / dlen          # neighbouring segments overlap by this much
        r_min = 1e-6 * diag / dlen           # minimum half width of a search interval
        tol = Float64(1e-6 * diag / dlen)    # refinement tolerance in t
        # Values at points of the ray are taken in float64 (as enclosures in
        # the search), so float32 rounding noise never decides a sign.
        o64 = [Float64(o[i]) for i in range(3)]
        d64 = [Float64(d[i]) for i in range(3)]
        ray64 = {"dx": d64[0], "dy": d64[1], "dz": d64[2]}

        def point64(t):
            t = Float64(t)
            return {v: o64[i] + t * d64[i] for i, v in enumerate("xyz")}

        def sgn(v):
            return dr.select(v > 0, 1, dr.select(v < 0, -1, 0))

        def sign_of(lo, hi):
            """+1 / -1 where [lo, hi] has one strict sign, else 0."""
            return dr.select(lo > 0, 1, dr.select(hi < 0, -1, 0))

        def enclose(v):
            """A float32 enclosure of a float64 point value (see POINT_ERROR)."""
            lo, hi = Float(v), Float(v)
            pad_abs = point_err
            return (lo - (dr.abs(lo) * 2.0**-22 + pad_abs), hi + (dr.abs(hi) * 2.0**-22 + pad_abs))

        def interval_of(level, idx, a, b):
            w = (b - a) / Float(UInt32(1) << UInt32(level))
            last = idx + 1 == (Int32(1) << level)
            return a + Float(idx) * w, dr.select(last, b, a + Float(idx + 1) * w)

        def advance(level, idx):
            """The next interval to the right in the implicit binary tree."""
            nxt = idx + 1
            tz = dr.minimum(Int32(dr.tzcnt(UInt32(nxt))), level)
            level, idx = level - tz, nxt >> tz
            return level, idx, (level == 0) & (idx == 1)

        def newton(t, F, g, t_lo, t_hi):
            tn = t - F / g
            return dr.select((tn > t_lo) & (tn < t_hi), tn, 0.5 * (t_lo + t_hi))

        # One loop; each lane is in one of these modes. Every iteration takes
        # one float64 point evaluation (F, g) and one interval evaluation.
        SEEK, SEARCH, REFINE, TINY_A, TINY_B, DONE = range(6)
        max_it = self.max_iterations

        def body(mode, t_cur, a, b, level, idx, t_lo, t_hi, t_n, F_a, s_lo, g_min,
                 t_hit, hit, unres, evals, iters):
            # ---- Next occupied cell (DDA, jumping over empty space) ----
            seek = mode == SEEK
            found, ta, tb = gridmod.next_occupied(dev, o, d, t_cur, t_end, seek)
            t_cur = dr.select(seek, tb, t_cur)
            a = dr.select(seek, dr.maximum(ta - margin, t_start), a)
            b = dr.select(seek, dr.minimum(tb + margin, t_end), b)
            level = dr.select(seek, 0, level)
            idx = dr.select(seek, 0, idx)
            mode = dr.select(seek, dr.select(found & (a <= b), SEARCH, DONE), mode)

            # ---- Evaluations ----
            searching = mode == SEARCH
            refining = mode == REFINE
            lo, hi = interval_of(level, idx, a, b)
            # [tm - r, tm + r] must cover [lo, hi]: the midpoint in float64
            # (exact), the half width rounded outward.
            tm64 = 0.5 * (Float64(lo) + Float64(hi))
            r = Float(0.5 * (Float64(hi) - Float64(lo))) * (1 + 2.0**-22)
            t_eval = dr.select(searching, tm64, t_n)
            F, g = evaluate([f, ge], {**point64(t_eval), **ray64}, m64)
            busy = mode != DONE
            iters = iters + dr.select(busy, 1, 0)
            if search_mode != "global":
                # Only searching lanes need it: a real branch skips the work
                # where a whole SIMD packet is refining.
                def seg_bounds(lo, hi):
                    r_ = bounds.segment_interval(ge if search_mode == "interval" else he,
                                                 o, d, lo, hi, m)
                    return r_.lo, r_.hi
                seg = Interval(*dr.if_stmt(args=(lo, hi), cond=searching, true_fn=seg_bounds,
                                           false_fn=lambda lo, hi: (Float(0), Float(0)),
                                           label="lgshape_bounds"))
            evals = evals + dr.select(busy, 1, 0) + dr.select(searching & (search_mode != "global"), 1, 0)

            # ---- Search step: exclude, bracket, split (or tiny) ----
            Fm = enclose(F)
            if search_mode == "interval":
                # Mean-value form: F(t) in F(t_m) + [g] [-r, r].
                g_lo, g_hi = seg.lo, seg.hi
                F_lo = Fm[0] + dr.minimum(r * g_lo, -r * g_hi)
                F_hi = Fm[1] + dr.maximum(r * g_hi, -r * g_lo)
                Fa = (Fm[0] - r * g_hi, Fm[1] - r * g_lo)
                Fb = (Fm[0] + r * g_lo, Fm[1] + r * g_hi)
            else:
                # Second-order Taylor form with G >= |h|: the seed's |g(t_m)| > G r.
                h_lo, h_hi = (seg.lo, seg.hi) if search_mode == "taylor" else (-G_glob, G_glob)
                G = dr.maximum(dr.abs(h_lo), dr.abs(h_hi))
                gm = enclose(g)
                q2 = 0.5 * r * r
                gr_lo, gr_hi = gm[0] * r, gm[1] * r
                ag = dr.maximum(dr.abs(gr_lo), dr.abs(gr_hi))
                g_lo, g_hi = gm[0] - G * r, gm[1] + G * r
                F_lo = Fm[0] - ag + dr.minimum(h_lo, 0) * q2
                F_hi = Fm[1] + ag + dr.maximum(h_hi, 0) * q2
                Fa = (Fm[0] - gr_hi + h_lo * q2, Fm[1] - gr_lo + h_hi * q2)
                Fb = (Fm[0] + gr_lo + h_lo * q2, Fm[1] + gr_hi + h_hi * q2)
            excluded = ((F_lo > 0) | (F_hi < 0)) & dr.isfinite(F)
            monotone = (g_lo > 0) | (g_hi < 0)
            s_a, s_b, s_m = sign_of(*Fa), sign_of(*Fb), sign_of(*Fm)
            left = monotone & (s_m != 0) & (s_a == -s_m)
            right = monotone & ~left & (s_m != 0) & (s_b == -s_m)
            empty = searching & (excluded | (monotone & (s_m != 0) & (s_a == s_m) & (s_b == s_m)))
            bracket = searching & ~empty & (left | right)
            tiny = searching & ~empty & ~bracket & ((r < r_min) | (level >= MAX_LEVEL))
            split = searching & ~empty & ~bracket & ~tiny
            # A tiny interval whose middle value cannot be told from 0 is a
            # hit (a tangent touch or singular point, to float precision).
            tiny_zero = tiny & (s_m == 0)
            tiny_check = tiny & ~tiny_zero

            # ---- Tiny interval: F at both ends decides (two iterations) ----
            tiny_a = mode == TINY_A
            tiny_b = mode == TINY_B
            s1, s2 = sgn(F_a), sgn(F)
            tiny_root = tiny_b & (s1 != s2)
            tiny_at_end = tiny_root & ((s1 == 0) | (s2 == 0))
            tiny_bracket = tiny_root & ~tiny_at_end
            tiny_none = tiny_b & ~tiny_root

            # ---- Refinement: safeguarded Newton in float64 ----
            same = sgn(F) == s_lo
            r_lo = dr.select(refining & same, t_n, t_lo)
            r_hi = dr.select(refining & ~same, t_n, t_hi)
            t_next = newton(t_n, F, g, r_lo, r_hi)
            # Where |F| / min |g| on the bracket (a proven distance to the root)
            # is below tol, t_n is within tol already: take its Newton step
            # kept in the bracket, never the safeguard's bisection midpoint.
            close = (F == 0) | (dr.abs(F) < Float64(g_min) * tol)
            t_next = dr.select(F == 0, t_n,                # t_n is the root itself
                     dr.select(close, dr.clip(t_n - F / g, r_lo, r_hi), t_next))
            # Converged: that, or a step below tol, or a bracket below tol.
            conv = refining & (close | (dr.abs(t_next - t_n) < tol) | (r_hi - r_lo < tol))

            # ---- Transitions ----
            lv_n, ix_n, seg_done = advance(level, idx)
            moving_on = empty | tiny_none
            level = dr.select(split, level + 1, dr.select(moving_on, lv_n, level))
            idx = dr.select(split, idx << 1, dr.select(moving_on, ix_n, idx))
            t_lo = dr.select(bracket, dr.select(left, Float64(lo), tm64),
                             dr.select(tiny_check, Float64(lo), dr.select(refining, r_lo, t_lo)))
            t_hi = dr.select(bracket, dr.select(left, tm64, Float64(hi)),
                             dr.select(tiny_check, Float64(hi), dr.select(refining, r_hi, t_hi)))
            s_lo = dr.select(bracket, dr.select(left, s_a, s_m), dr.select(tiny_bracket, s1, s_lo))
            g_min = dr.select(bracket, dr.minimum(dr.abs(g_lo), dr.abs(g_hi)),
                              dr.select(tiny_bracket, 0.0, g_min))
            F_a = dr.select(tiny_a, F, F_a)
            t_n = dr.select(bracket, newton(tm64, F, g, t_lo, t_hi),
                  dr.select(tiny_check, t_lo,
                  dr.select(tiny_a, t_hi,
                  dr.select(tiny_bracket, 0.5 * (t_lo + t_hi),
                  dr.select(refining, t_next, t_n)))))

            first_hit = (tiny_zero | (any_hit & (bracket | tiny_bracket)) | tiny_at_end | conv)
            if any_hit:
                t_found = dr.select(tiny_zero, tm64, dr.select(tiny_at_end, dr.select(s1 == 0, t_lo, t_hi),
                                    dr.select(conv, t_next, 0.5 * (t_lo + t_hi))))
            else:
                t_found = dr.select(tiny_zero, tm64, dr.select(tiny_at_end, dr.select(s1 == 0, t_lo, t_hi), t_next))
            hit = hit | first_hit
            unres = unres | (first_hit & (tiny_zero | tiny_at_end)) | (tiny_bracket & ~hit)
            t_hit = dr.select(first_hit, Float(t_found), t_hit)

            mode = dr.select(first_hit, DONE,
                   dr.select(bracket | tiny_bracket, REFINE,
                   dr.select(tiny_check, TINY_A,
                   dr.select(tiny_a, TINY_B,
                   dr.select(moving_on, dr.select(seg_done, SEEK, SEARCH),
                   dr.select(tiny_b, SEARCH, mode))))))
            mode = dr.select(iters >= max_it, DONE, mode)
            return (mode, t_cur, a, b, level, idx, t_lo, t_hi, t_n, F_a, s_lo, g_min,
                    t_hit, hit, unres, evals, iters)

        def z(T):
            return dr.zeros(T, n)
        mode0 = dr.select(active, SEEK, DONE) + z(Int32)
        state = (mode0, Float(t_start), z(Float), z(Float), z(Int32), z(Int32),
                 z(Float64), z(Float64), z(Float64), z(Float64), z(Int32), z(Float),
                 dr.full(Float, math.inf, n), z(Bool), z(Bool), z(UInt32), z(UInt32))
        out = dr.while_loop(state=state, cond=lambda mode, *_: mode != DONE, body=body,
                            label="lgshape_search")
        t_hit, hit, unres, evals, iters = out[12:17]
        capped = iters >= max_it
        hit = hit & ~capped
        return RayResult(dr.select(hit, t_hit, math.inf), hit, evals, iters, capped, unres)
