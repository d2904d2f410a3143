"""The guaranteed ray search (Kalra & Barr 1989) over the pruning grid.

The ray is clipped to the surface's box and moved to its entry
(:func:`lgshape.evaluator.prepare_rays`); a DDA visits the occupied cells of
the pruning grid nearest first (:mod:`lgshape.grid`); in each cell the
segment [a, b] is searched by stackless bisection (an implicit binary tree:
level and index), each interval decided by the Kalra-Barr test of
:meth:`lgshape.evaluator.Evaluator.test` (no root, one root, or split).

**Phases**, each a function of its own:

- enter (:func:`_enter`): a clip (a quadric's exact form, or a polynomial's
  Bezier hull) that settles many rays at once, and the first walk;
- walk (:func:`_walk`): the DDA to the next occupied cell (a nested loop
  of :class:`lgshape.grid.Walker`); its segment, widened by a margin,
  becomes the root of the bisection;
- step (:func:`_step`): one evaluation and the decision it allows; the rare
  cases below the minimum width in :func:`_small`;
- refine (:func:`_refine`): safeguarded Newton in float64 in the bracket, in
  a loop of its own after the search, with only its own state.

:func:`_locate` runs walk and step in one symbolic loop (``lgshape_search``):
lanes of one SIMD packet that walk and lanes that search share its
iterations. Refinement needs none of the search's state, so it runs after it
(``lgshape_refine``) with six variables (Dr.Jit merges every state variable of
a symbolic loop with a select per iteration).

**Modes and outcomes.** A lane's ``mode`` says what it does in the next
iteration, its ``outcome`` what it has found:

============  ==============================  ===========================  =================
mode          the iteration                   next mode                    outcome it sets
============  ==============================  ===========================  =================
``SEEK``      walk to the next occupied cell  SEARCH (same iteration),     NONE (no cell),
              (then as SEARCH)                END (no cell left)           CAPPED (stuck)
``SEARCH``    test the current interval       SEARCH (next or half),       BRACKET, HIT
                                              SEEK (segment done),
                                              TINY_A (tiny, open), END
``TINY_A``    F at the tiny interval's left   TINY_B
              end (``probe``)
``TINY_B``    F at its right end; both signs  SEARCH / SEEK (no root),     BRACKET, HIT
              decide                          EDGE (one end undefined),
                                              END
``EDGE``      F at the middle of [t_lo, t_hi] EDGE, SEARCH / SEEK (none),  BRACKET, HIT
              (towards the domain's edge)     END
``END``       nothing                         END                          (final)
============  ==============================  ===========================  =================

Outcomes: ``WALKING`` (still looking), ``NONE`` (no root in the window),
``BRACKET`` (one root in [t_lo, t_hi]; :func:`_refine` makes it a HIT),
``HIT`` (a root at t), ``CAPPED`` (the iteration bound reached: reported as
a miss and counted, never silently). Any lane that reaches
``max_iterations`` ends CAPPED.

**Refinement and tiny intervals.** A bracketed single root is refined by
safeguarded Newton in float64 (bisection where a step leaves the bracket)
until the step, or the proven distance |F| / min |g|, is below 1e-6 of the
box diagonal. Intervals are visited left to right, so the first root found
is the nearest. Below a minimum width (1e-6 of the diagonal) an interval
that cannot be excluded is a root where F changes sign across it (and is
bounded there), or where F at its middle is within its error bound of 0 (a
tangent touch or singular point, counted as ``unresolved``); otherwise the
search goes on after it. Where one end of a smallest interval is undefined,
a root between the domain's edge and the defined end is looked for by
bisecting towards the edge (``EDGE``).

**The window [t_min, t_max].** The search starts at t_min (or at the box's
entry), but its tree, the cells' segments and their bisection, is the ray's
in the box whatever t_max: t_max only drops the roots past it (the walk
stops at the first cell whose segment starts past it, a segment's search at
its first interval that does; an any-hit query takes a sign change or a
bracket as a hit only where it ends before t_max, and refines a bracket that
reaches past it). So the root found with t_max = inf is the one found (with
the same t) for every t_max beyond it, and ``occluded`` agrees.

**Every ray ends.** Rays with a zero, infinite or NaN direction, or a NaN
origin, are misses. The grid walk is bounded by the number of cells a line
can cross; the search by ``max_iterations``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import drjit as dr

from . import grid as gridmod
from .arraymath import exact_arithmetic
from .evaluator import Evaluator, prepare_rays, sign_known
from .expr import raypoly

#: Bisection depth bound inside one cell segment.
MAX_LEVEL = 22

#: The segment the walk hands the search (interval mode, plain
#: expressions): from the entry of the next occupied cell over at least
#: this many edges of the smallest cell, whatever the cells after the first
#: one hold (an empty cell in it costs nothing to prove: the bounds exclude
#: it). One test decides it where f is simple along it; the bisection
#: splits it where not; the walk does not step through the cells inside it
#: (a dependent gather each). A table form takes one cell at a time (each
#: cell has its own rows), and so do the seed's modes ("taylor", "global"),
#: whose test |g(t_m)| > G r needs short intervals.
SPAN_CELLS = 8

#: Bezier-clipping steps (from both ends) before the walk, for a polynomial
#: f (:func:`_clip_polynomial`); 0: none.
POLY_CLIP_STEPS = 1

# A lane's outcome (_Lane.outcome) and mode (_Lane.mode): the table above.
WALKING, NONE, BRACKET, HIT, CAPPED = range(5)
SEEK, SEARCH, TINY_A, TINY_B, EDGE, END = range(6)


@dataclass
class RayResult:
    """Per-ray output of :meth:`lgshape.trace.Surface.trace` (Dr.Jit arrays)."""
    t: object            # Float: nearest root, inf where none
    hit: object          # Bool
    evals: object        # UInt32: point + interval evaluations
    iterations: object   # UInt32: search + refinement iterations
    capped: object       # Bool: reached the iteration bound
    unresolved: object   # Bool: hit decided at the minimum width (tangent/singular)
    t64: object = None   # Float64: the same t before rounding to float32


def empty_result(Float) -> RayResult:
    """The RayResult of no rays."""
    Float64 = dr.float64_array_t(Float)
    return RayResult(Float(), dr.mask_t(Float)(), dr.uint32_array_t(Float)(),
                     dr.uint32_array_t(Float)(), dr.mask_t(Float)(), dr.mask_t(Float)(),
                     Float64())


def search(surf, o, d, t_min, t_max, active, any_hit) -> RayResult:
    """The search for the rays o + t d, t in [t_min, t_max], of a
    :class:`~lgshape.trace.Surface`: the first root, or for ``any_hit`` any
    proven root (Dr.Jit code, traced into the caller's kernels)."""
    with exact_arithmetic(type(o.x)):        # IEEE division and sqrt on CUDA too
        return _search_traced(surf, o, d, t_min, t_max, active, any_hit)


def _search_traced(surf, o, d, t_min, t_max, active, any_hit) -> RayResult:
    Float = type(o.x)
    K = surf._kernel_data(Float)
    n = max(dr.width(o), dr.width(d))
    active, t_start, rays = prepare_rays(K, o, d, t_min, t_max, active, n)
    ev = Evaluator(surf, K, rays)
    max_it = surf.max_iterations

    walker, lane = _enter(ev, active, any_hit)
    lane = _locate(ev, walker, lane, any_hit, max_it)
    # (an any-hit query refines only the brackets that reach past t_max)
    lane = _refine(ev, lane, max_it)
    capped = lane.outcome == CAPPED
    # t_max drops the roots past it; the search did not stop there
    hit = (lane.outcome == HIT) & (lane.t <= rays.s_max64)
    t64 = dr.select(hit, t_start + lane.t, math.inf)
    return RayResult(Float(t64), hit, lane.evals, lane.iters, capped, lane.unres & hit, t64)


@dataclass
class _Lane:
    """A ray's search state (Dr.Jit arrays, one entry per ray; the state of
    the ``lgshape_search`` loop)."""
    mode: object         # Int32: what the next iteration does (SEEK ... END)
    outcome: object      # Int32: what the search has found (WALKING ... CAPPED)
    s_cur: object        # Float: where the walk goes on from (the cell's exit)
    a: object            # Float: the cell's segment [a, b]
    b: object
    level: object        # Int32: the interval of the bisection in [a, b]
    idx: object          # Int32
    t: object            # Float64: the root: the hit, or refinement's start in a bracket
    probe: object        # Float64: where TINY_A, TINY_B and EDGE take F next
    t_lo: object         # Float64: a bracket [t_lo, t_hi] (or a tiny interval)
    t_hi: object
    s_lo: object         # Int32: sign of F at t_lo
    s_a: object          # Int32: sign of F at a tiny interval's left end (TINY_A's)
    edge_def: object     # Int32: the defined end of an edge search (+1 left, -1 right)
    g_min: object        # Float64: min |g| over the bracket (0: unknown)
    bounded: object      # Bool: F bounded over the tiny interval
    unres: object        # Bool: decided at the minimum width
    evals: object        # UInt32
    iters: object        # UInt32
    rng: tuple           # the rows of the cell (table forms), a (start, end) per group

    @classmethod
    def start(cls, ev, active):
        K = ev.K
        Float, Float64 = K.m.Float, K.m64.Float
        Int32, UInt32, Bool = (dr.int32_array_t(Float), dr.uint32_array_t(Float),
                               dr.mask_t(Float))
        n = dr.width(ev.rays.span)

        def z(T):
            return dr.zeros(T, n)
        return cls(mode=dr.select(active, SEEK, END) + z(Int32),
                   outcome=dr.select(active, WALKING, NONE) + z(Int32),
                   s_cur=z(Float), a=z(Float), b=z(Float), level=z(Int32), idx=z(Int32),
                   t=z(Float64), probe=z(Float64), t_lo=z(Float64), t_hi=z(Float64),
                   s_lo=z(Int32), s_a=z(Int32), edge_def=z(Int32), g_min=z(Float64),
                   bounded=z(Bool), unres=z(Bool), evals=z(UInt32), iters=z(UInt32),
                   rng=tuple((z(UInt32), z(UInt32))
                             for _ in (K.tables.groups if ev.tabled else ())))


@dataclass
class _Rare:
    """What :func:`_step` hands :func:`_small` (Dr.Jit arrays per lane)."""
    mode: object         # Int32: the lane's mode in this iteration
    tiny: object         # Bool: a SEARCH interval below the minimum width, undecided
    F: object            # Float64: F at this iteration's point, and its error bound
    eF: object
    tm: object           # Float64: the middle of the interval tested
    lo: object           # Float: the interval tested
    hi: object
    zero_mid: object     # Bool: F(tm) within its error bound of 0, F defined and bounded
    bounded: object      # Bool: F bounded over the interval
    g_min: object        # Float64: min |g| over it where g keeps one sign, else 0


def _newton(t, F, g, t_lo, t_hi):
    tn = t - F / g
    return dr.select((tn > t_lo) & (tn < t_hi), tn, 0.5 * (t_lo + t_hi))


def _first_guess(t, F, g, c2, t_lo, t_hi):
    """Where refinement starts in a new bracket: the root nearest t of the
    quadratic F + g s + c2 s^2 (F's quadratic form about t, with F's point
    value), where it lies in the bracket; else Newton's step from t."""
    disc = g * g - 4.0 * c2 * F
    den = g + dr.select(g >= 0, 1.0, -1.0) * dr.sqrt(dr.maximum(disc, 0.0))
    tq = t - 2.0 * F / den
    ok = (disc >= 0) & (den != 0) & (tq > t_lo) & (tq < t_hi)
    return dr.select(ok, tq, _newton(t, F, g, t_lo, t_hi))


def _enter(ev: Evaluator, active, any_hit):
    """The rays' start: a clip (a quadric's, :func:`_clip_quadric`, or a
    polynomial's, :func:`_clip_polynomial`) and the first :func:`_walk`.
    Returns (walker, lane); lanes whose mode is not END go on to
    :func:`_locate`."""
    # the walk ends where the cells' segments (which reach back by the
    # margin) start past t_max (they do not end at t_max: see Rays.s_max)
    walker = gridmod.Walker(ev.K.grid, ev.rays.g_org, ev.rays.d32,
                            dr.minimum(ev.rays.span, ev.rays.s_max + 2 * ev.rays.margin),
                            rows_up=ev.K.tables.up if ev.tabled else None,
                            entering=ev.rays.entering)
    lane = _Lane.start(ev, active)
    # Clip, then the first walk before the loop: a ray that meets no
    # occupied cell ends there, and a packet of such rays never runs the
    # loop's body. (Not after a quadric's clip, which settles most rays: a
    # walk there costs more than it saves, docs/kernel-plan.md.)
    if ev.mode == "interval" and ev.surf.quadric:
        _clip_quadric(ev, lane, active, any_hit)
    else:
        if ev.poly is not None and POLY_CLIP_STEPS > 0:
            _clip_polynomial(ev, lane, active)
        _walk(ev, walker, lane)
    return walker, lane


def _locate(ev: Evaluator, walker, lane: _Lane, any_hit, max_it) -> _Lane:
    """The loop over the occupied cells a ray crosses, nearest first, after
    :func:`_enter`. One iteration: :func:`_walk` to the next cell where a
    lane needs one, one evaluation (the interval test of the current
    interval, or a point), and :func:`_step`, the search's decision. Ends
    with a hit, a bracket to refine, no root or the cap."""

    def body(lane):
        lane = replace(lane)
        _walk(ev, walker, lane)
        _step(ev, lane, any_hit, max_it)
        return (lane,)
    (lane,) = dr.while_loop(state=(lane,), cond=lambda lane: lane.mode != END, body=body,
                            label="lgshape_search")
    return lane


def _clip_quadric(ev: Evaluator, lane: _Lane, active, any_hit):
    """Clip, for a quadric (f of degree <= 2), before any walk: F's
    quadratic form over the whole ray is exact (to rounding). Where it
    excludes a root, no root; where it brackets the first root, refinement
    (for an any-hit query, a hit); else the walk starts where the first
    root may be (:meth:`Evaluator.clip`)."""
    free, first, crossed, b_lo, b_hi, s_lo = ev.clip(
        dr.zeros(ev.K.m.Float, dr.width(ev.rays.span)), ev.rays.span, active)
    lane.s_cur = first
    lane.mode = dr.select(free | crossed, END, lane.mode)
    # (an any-hit query's bracket reaching past t_max is refined: its root
    # may lie beyond)
    taken = dr.select(b_hi <= ev.rays.s_max64, HIT, BRACKET) if any_hit else BRACKET
    lane.outcome = dr.select(free, NONE, dr.select(crossed, taken, lane.outcome))
    lane.t_lo = dr.select(crossed, b_lo, lane.t_lo)
    lane.t_hi = dr.select(crossed, b_hi, lane.t_hi)
    lane.s_lo = dr.select(crossed, s_lo, lane.s_lo)
    lane.t = dr.select(crossed, 0.5 * (b_lo + b_hi), lane.t)
    lane.evals = lane.evals + dr.select(active, 1, 0)


def _clip_polynomial(ev: Evaluator, lane: _Lane, active):
    """Clip, for a polynomial f (the ray's coefficients), before any walk:
    the convex hulls of F's Bernstein coefficients prove that no root lies
    before ``first`` on the ray, or none at all
    (:func:`lgshape.expr.raypoly.clip_first_root`); the walk starts there.
    Rays that miss the surface, most of a camera's rays in the box, end
    here without walking the empty cells."""
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


def _walk(ev: Evaluator, walker, lane: _Lane):
    """Walk: lanes in SEEK go to the next occupied cell (the DDA of
    :class:`lgshape.grid.Walker`); its segment (over SPAN_CELLS cells where
    the search takes spans), widened by the margin, becomes the root of the
    bisection; no cell left: no root."""
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
    cell = found & (a <= b) & (a <= R.s_max)
    lane.outcome = dr.select(seek & stuck, CAPPED,            # a walk that cannot end
                   dr.select(seek & ~cell, NONE, lane.outcome))
    lane.mode = dr.select(seek, dr.select(cell, SEARCH, END), lane.mode)


def _step(ev: Evaluator, lane: _Lane, any_hit, max_it):
    """Search: one evaluation and the decision it allows. A SEARCH lane
    tests its interval of the bisection (the whole cell first): no root ->
    the next interval (the next cell after the last); one root -> a bracket
    (to refine); undecided -> split, or, below the minimum width, the rare
    cases of :func:`_small` (tiny intervals, edges of f's domain), in a
    branch that a SIMD packet runs only where one of its lanes needs it."""
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
    P, B, c2 = ev.point_and_bounds(dr.select(searching, tm, lane.probe), lo, hi, lane.rng,
                                   searching & (ev.mode != "global"), want)
    F, eF, g, eg, _ = P
    T = ev.test(lo, hi, lane.rng, searching, P, B)
    busy = mode != END
    lane.iters = lane.iters + dr.select(busy, 1, 0)
    lane.evals = lane.evals + dr.select(busy, 1, 0) + dr.select(searching, UInt32(T.evals - 1), 0)

    # ---- no root: the next interval; one root: a bracket; else split ----
    # (an any-hit query stops at any proven root: a sign change will do,
    # on an interval that ends before t_max)
    cross = T.crossing & ~T.bracket & any_hit
    if any_hit:
        cross = cross & (Float64(hi) <= R.s_max64)
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
        # (one that reaches past t_max is refined: its root may lie beyond)
        beyond = br & (T.b_hi > R.s_max64)
        lane.t = dr.select(br, 0.5 * (T.b_lo + T.b_hi), dr.select(cross, tm, lane.t))
        br = br | cross
        lane.outcome = dr.select(br, dr.select(beyond, BRACKET, HIT), lane.outcome)
    else:
        lane.t = dr.select(br, _first_guess(tm, F, g, c2, T.b_lo, T.b_hi), lane.t)
        lane.outcome = dr.select(br, BRACKET, lane.outcome)
    lane.mode = dr.select(br, END, dr.select(T.empty & seg_done, SEEK, mode))

    # ---- the rare cases ----
    rare = tiny | (mode == TINY_A) | (mode == TINY_B) | (mode == EDGE)

    def small(lane, x):
        lane = replace(lane)
        _small(ev, lane, x, any_hit)
        return lane
    x = _Rare(mode=mode, tiny=tiny, F=F, eF=eF, tm=tm, lo=lo, hi=hi,
              zero_mid=T.defined & T.bounded & (T.s_m == 0), bounded=T.bounded, g_min=T.g_min)
    new = dr.if_stmt(args=(lane, x), cond=rare, true_fn=small,
                     false_fn=lambda lane, x: lane, label="lgshape_small")
    for f in fields(lane):
        setattr(lane, f.name, getattr(new, f.name))
    # the next interval starts past t_max: so does the rest of the segment
    # (intervals are visited left to right); the next cell's segment, which
    # reaches back by the margin, may not (the walk tells)
    lo_next, _ = _interval_of(lane.level, lane.idx, lane.a, lane.b)
    lane.mode = dr.select((lane.mode == SEARCH) & (lo_next > R.s_max), SEEK, lane.mode)
    capped = (lane.mode != END) & (lane.iters >= max_it)
    lane.outcome = dr.select(capped, CAPPED, lane.outcome)
    lane.mode = dr.select(capped, END, lane.mode)


def _small(ev: Evaluator, lane: _Lane, x: _Rare, any_hit):
    """Intervals below the minimum width, and the edges of f's domain.

    A tiny interval (``x.tiny``) whose middle value is within its error
    bound of 0 (``x.zero_mid``) is a hit: a tangent touch or singular point,
    to float precision. Else F at both its ends decides (TINY_A, TINY_B: one
    point each); a bracket found so is resolved where g keeps one sign on the
    interval. Where one end lies outside f's domain, the root may lie between
    the domain's edge and the defined end: found by bisecting towards the
    edge, watching the sign (EDGE). The masks below are disjoint: each lane
    takes one transition."""
    R = ev.rays
    Float64 = ev.K.m64.Float
    tiny_zero = x.tiny & x.zero_mid
    tiny_check = x.tiny & ~tiny_zero

    # ---- tiny interval: F at both ends decides (two iterations) ----
    tiny_a, tiny_b = x.mode == TINY_A, x.mode == TINY_B
    s_here = sign_known(x.F, x.eF)
    s1, s2 = lane.s_a, s_here              # the signs at the left and right ends
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
    # [t_lo, t_hi] has one defined end (edge_def: +1 the left one, -1 the
    # right one) of sign s_lo; each step looks at the middle, the probe.
    t_lo, t_hi, t_n = lane.t_lo, lane.t_hi, lane.probe
    edge = x.mode == EDGE
    left_def = lane.edge_def > 0
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
    # the interval looked at next: the tiny one, or the edge search's half
    # (an edge bracket lies between the middle and the defined end)
    eb_lo, eb_hi = dr.select(left_def, t_lo, t_n), dr.select(left_def, t_n, t_hi)
    t_lo = dr.select(tiny_check, Float64(x.lo),
           dr.select(edge_bracket, eb_lo, dr.select(edge, e_lo, t_lo)))
    t_hi = dr.select(tiny_check, Float64(x.hi),
           dr.select(edge_bracket, eb_hi, dr.select(edge, e_hi, t_hi)))
    mid = 0.5 * (t_lo + t_hi)
    lane.s_lo = dr.select(tiny_bracket, s1, dr.select(edge_start, s_def,
                dr.select(edge_bracket & ~left_def, s_here, lane.s_lo)))
    new_bracket = tiny_bracket | edge_bracket
    # a tiny bracket where g keeps one sign (``g_min``, kept from the tiny
    # interval's test) is a bracket as the test's are: one simple root, its
    # ends' signs from point values where the test's bounds could not tell
    # them (a root within rounding of a float32 end of the bisection)
    mono_bracket = tiny_bracket & (lane.g_min > 0)
    lane.g_min = dr.select(new_bracket & ~mono_bracket, 0.0,
                           dr.select(tiny_check, x.g_min, lane.g_min))
    lane.bounded = dr.select(tiny_check, x.bounded, lane.bounded)
    lane.s_a = dr.select(tiny_a, s_here, lane.s_a)
    lane.edge_def = dr.select(edge_start, dr.select(s1 == 2, -1, 1), lane.edge_def)
    found = tiny_zero | edge_zero | tiny_at_end
    # where the next point is taken (TINY_A: the left end, TINY_B: the
    # right one, EDGE: the middle), and the root found (a refinement's start)
    lane.probe = dr.select(tiny_check, t_lo, dr.select(tiny_a, t_hi,
                 dr.select(edge_start | edge, mid, lane.probe)))
    at_end = dr.select(s1 == 0, t_lo, t_hi)      # (the tiny interval's ends)
    lane.t = dr.select(new_bracket | edge_zero, mid,
             dr.select(tiny_zero, x.tm, dr.select(tiny_at_end, at_end, lane.t)))
    lane.t_lo, lane.t_hi = t_lo, t_hi
    # a bracket found here is unresolved too (decided at the minimum width),
    # unless g keeps one sign there
    lane.unres = lane.unres | found | (new_bracket & ~mono_bracket & (not any_hit))
    if any_hit:
        # (a bracket that reaches past t_max is refined: its root may lie beyond)
        found = found | (new_bracket & (t_hi <= R.s_max64))
    lane.outcome = dr.select(found, HIT, dr.select(new_bracket, BRACKET, lane.outcome))
    # the next mode (each line overrides the ones above it, on disjoint masks)
    mode = dr.select(tiny_b, SEARCH, lane.mode)       # TINY_B without a root
    mode = dr.select(moving_on, dr.select(seg_done, SEEK, SEARCH), mode)
    mode = dr.select(edge_start, EDGE, mode)
    mode = dr.select(tiny_a, TINY_B, mode)
    mode = dr.select(tiny_check, TINY_A, mode)
    lane.mode = dr.select(found | new_bracket, END, mode)


def _interval_of(level, idx, a, b):
    """The idx-th of the 2^level equal parts of [a, b] (the last one ends
    at b exactly)."""
    Float = type(a)
    UInt32, Int32 = dr.uint32_array_t(Float), dr.int32_array_t(Float)
    w = (b - a) / Float(UInt32(1) << UInt32(level))
    last = idx + 1 == (Int32(1) << level)
    return a + Float(idx) * w, dr.select(last, b, a + Float(idx + 1) * w)


def _advance(level, idx):
    """The next interval to the right in the implicit binary tree, and
    whether the tree is done."""
    nxt = idx + 1
    tz = dr.minimum(type(idx)(dr.tzcnt(dr.uint32_array_t(type(idx))(nxt))), level)
    level, idx = level - tz, nxt >> tz
    return level, idx, (level == 0) & (idx == 1)


def _refine(ev: Evaluator, lane: _Lane, max_it) -> _Lane:
    """Refine: safeguarded Newton in float64 in each bracket (bisection
    where a step leaves it) until the step, the bracket, or the proven
    distance to the root |F| / min |g|, is below the tolerance. A loop of
    its own after the search, with only its own state."""
    R = ev.rays
    Float64 = ev.K.m64.Float

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
        # that step only where g is a slope the bracket allows (its sign,
        # -s_lo, and |g| >= min |g|): then it stays within tol of the root.
        # Else (g NaN, 0 or off: the point slope at a singular point of
        # the distance, 0 / 0 on a torus's axis) t itself, within tol
        g_ok = (g * Float64(lane.s_lo) < 0) & (dr.abs(g) >= lane.g_min)
        t_close = dr.select(g_ok, dr.clip(t - F / g, r_lo, r_hi), t)
        t_next = dr.select(F == 0, t, dr.select(close, t_close, t_next))
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
