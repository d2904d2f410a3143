"""Quadratic forms along a ray segment: a tighter enclosure than intervals.

On the segment t = t_m + s, |s| <= r, of a ray, every node of an expression
gets a :class:`Quad` (c0, c1, c2, R): a quadratic in s and a remainder bound,

    value(t_m + s)  in  c0 + c1 s + c2 s^2 + [-R, R]   for every |s| <= r

(at the points where the node is defined; see :mod:`lgshape.interval` for
that contract). The coordinates x, y, z are linear in s, so sums and
products of them stay exact up to degree 2; the terms of degree 3 and 4 of a
product are bounded over |s| <= r and go to the remainder. The enclosure of
a polynomial f therefore misses its range by O(r^3), where natural interval
arithmetic and the mean-value form miss it by O(r) and O(r^2): a ray that
passes near the surface without crossing it is told apart at a coarser
split, and a cell it grazes is often excluded in one test.

sin, cos and exp keep the second-order part of their Taylor expansion
about c0 (:func:`_smooth`) where it is narrower than their interval rule.
The other ops that are not polynomial (sqrt, log, division by a
non-constant) take their arguments' ranges (:func:`quad_range`) through
the interval rules of :mod:`lgshape.interval` and give a constant form;
min, max and abs keep the form of the argument that provably wins (or its
sign), else do the same. For a distance such as sqrt((x-a)^2 + ...) - r the
range is exact up to rounding, since the square sum is exact. The slope of
such a distance, U' / (2 sqrt U) with U = v_1^2 + ... + v_k^2, has no
finite interval rule where U's range reaches 0; there it is bounded by
Cauchy-Schwarz, |sum v_i v_i'| / |v| <= |v'| (:func:`_norm_bound`).

Rounding: the coefficients are computed in the array's precision, rounded
to nearest; each op adds to R a bound of the rounding of every term it
computes, ``GAMMA * u`` times the product (or sum) of its arguments'
magnitudes (the largest value each can take on the segment), which covers
the few roundings of each coefficient and of R itself. Anything infinite
or NaN makes the range infinite (:func:`quad_range`): no information, never
a wrong one.
"""
from __future__ import annotations

import math

from .. import interval as iv
from ..arraymath import powi, zero_like
from .evaluate import _lookup, constant
from .node import Expr, product_chain, topological
from . import ops
from .ops import OPS

#: Roundings covered per op, in units of ``m.u`` (the unit roundoff with a
#: factor 2 of margin): a coefficient is a sum of at most three products
#: (3 roundings), R a sum of at most five (5), with room to spare.
GAMMA = 16.0


class Quad:
    """c0 + c1 s + c2 s^2 + [-R, R] over |s| <= r (arrays, R >= 0)."""
    __slots__ = ("c0", "c1", "c2", "R")

    def __init__(self, c0, c1, c2, R):
        self.c0, self.c1, self.c2, self.R = c0, c1, c2, R

    def __repr__(self):
        return f"Quad({self.c0}, {self.c1}, {self.c2}, +-{self.R})"


class Segment:
    """The powers of the half width r (rounded up) shared by a whole
    evaluation, and the array namespace."""

    def __init__(self, m, r):
        self.m = m
        up = 1.0 + 4.0 * m.u
        self.r = r
        self.r2 = r * r * up
        self.r3 = self.r2 * r * up
        self.r4 = self.r2 * self.r2 * up
        self.g = GAMMA * m.u

    def mag(self, q: Quad):
        """max |q| over the segment (rounded down by at most a few ulp,
        which the callers' GAMMA covers)."""
        m = self.m
        return m.abs(q.c0) + m.abs(q.c1) * self.r + m.abs(q.c2) * self.r2 + q.R

    def slack(self, M):
        return self.g * M + self.m.tiny


def coordinate(seg: Segment, e, d, tm, offset=None):
    """The form of a coordinate e + t d (t = tm + s) of the ray, with the
    rounding of e, of tm d and of their sum (and of an interval ``offset``,
    e.g. the enclosure of a grid centre) in R."""
    m = seg.m
    c0 = e + tm * d
    R = (m.abs(e) + m.abs(tm * d)) * m.eps + m.tiny
    if offset is not None:
        lo, hi = offset
        mid = 0.5 * (lo + hi)
        c0 = c0 + mid
        R = R + (hi - lo) * 0.5 + m.abs(c0) * m.eps + m.tiny
    return Quad(c0, d, zero_like(d), R)


def from_interval(m, a: iv.Interval) -> Quad:
    """A constant form covering a (unknown where a is not finite or empty)."""
    ok = (a.lo <= a.hi) & (a.lo > -math.inf) & (a.hi < math.inf)
    mid = m.select(ok, 0.5 * (a.lo + a.hi), 0.0)
    half = 0.5 * (a.hi - a.lo)
    R = m.select(ok, half + (m.abs(a.lo) + m.abs(a.hi)) * m.eps + m.tiny, math.inf)
    z = zero_like(mid)
    return Quad(mid, z, z, R)


def _plain(m, v) -> Quad:
    """A plain (computed) value: rounding padded as :func:`interval.promote`."""
    z = zero_like(v)
    return Quad(v, z, z, m.abs(v) * m.eps + m.tiny)


def quad_env(m, e32, d32, lo, hi, offsets=None, local=None):
    """The segment e + [lo, hi] d of a ray (lists of three arrays e and d)
    as a :class:`Segment` about its middle (computed in the arrays'
    precision; r rounded up so that [tm - r, tm + r] covers [lo, hi]) and
    the forms of its coordinates, plus the plain direction dx, dy, dz;
    ``offsets``: intervals added to the coordinates (a grid centre);
    ``local``: more coordinates by name, each with its own offset interval
    (in x, y, z order)."""
    tm = 0.5 * (lo + hi)
    r = m.maximum(tm - lo, hi - tm) * (1.0 + 4.0 * m.u)
    seg = Segment(m, r)
    env = {v: coordinate(seg, e32[i], d32[i], tm, None if offsets is None else offsets[i])
           for i, v in enumerate("xyz")}
    for i, (name, off) in enumerate((local or {}).items()):
        env[name] = coordinate(seg, e32[i], d32[i], tm, off)
    env.update({"d" + v: d32[i] for i, v in enumerate("xyz")})
    return seg, env


def quad_range(seg: Segment, q: Quad) -> iv.Interval:
    """The interval of q over |s| <= r: the quadratic's values at the ends
    and at its vertex where it lies inside, widened by R and the rounding.
    NaN or overflow anywhere gives infinite bounds."""
    m = seg.m
    with m.errstate():
        return _range(seg, q)


def quad_ends(seg: Segment, q: Quad, at=None):
    """Bounds of q at s = -r and s = +r (or at s = -at and +at, 0 <= at <=
    r): (lo_a, hi_a, lo_b, hi_b), each the quadratic's value there widened
    by R and the rounding; NaN or overflow gives infinite bounds."""
    m = seg.m
    with m.errstate():
        pa, pb, w = _ends(seg, q)
        if at is not None:
            pa = q.c0 - q.c1 * at + q.c2 * (at * at)
            pb = q.c0 + q.c1 * at + q.c2 * (at * at)
        return (_finite_lo(m, pa - w), _finite_hi(m, pa + w),
                _finite_lo(m, pb - w), _finite_hi(m, pb + w))


def quad_clip(seg: Segment, q: Quad):
    """What q's enclosure tells about the first root on the segment:
    (free, first, cross, crossed, up).

    - ``free``: it excludes 0 over the whole segment (no root);
    - ``first`` >= -r: no root in [-r, first) (-r where none is proven);
    - ``crossed``: q's enclosure at ``cross`` > first has the sign opposite
      to the one it starts with, so where f is continuous (a polynomial) a
      root lies in (first, cross], the first one;
    - ``up``: the enclosure starts above 0 (where ``first`` > -r, q > 0 on
      [-r, first]).

    The candidates are the first roots of q(s) = +-w (w: R and the
    rounding), from the side q's enclosure starts on, each moved a little
    outward; ``first`` is kept only where the range of the quadratic over
    [-r, first], computed as :func:`quad_range` does (ends and vertex,
    widened by w), excludes 0, and ``cross`` only where q's enclosure there
    excludes 0. The solves are proposals; the ranges are the proofs."""
    m = seg.m
    with m.errstate():
        r = seg.r
        c0, c1, c2 = q.c0, q.c1, q.c2
        pa, _, w = _ends(seg, q)
        whole = _range(seg, q)
        free = (whole.lo > 0) | (whole.hi < 0)
        up = pa - w > 0                 # the enclosure starts above 0
        w_up = m.select(up, w, -w)
        s1 = _root_after(m, c2, c1, c0 - w_up, -r, r)
        cand = m.minimum(s1, r)
        cand = cand - 16.0 * m.eps * (m.abs(cand) + r)
        # the proof: q's range over [-r, cand]
        qc = c0 + cand * (c1 + cand * c2)
        lo, hi = m.minimum(pa, qc), m.maximum(pa, qc)
        c2s = m.select(c2 != 0, c2, 1.0)
        sv = -0.5 * c1 / c2s
        inside = (c2 != 0) & (sv > -r) & (sv < cand)
        pv = c0 - 0.25 * c1 * (c1 / c2s)
        lo = m.select(inside, m.minimum(lo, pv), lo)
        hi = m.select(inside, m.maximum(hi, pv), hi)
        ok = (cand > -r) & m.select(up, lo - w > 0, hi + w < 0)
        # where the enclosure is surely past 0: the first root of q = -+w
        s2 = _root_after(m, c2, c1, c0 + w_up, s1, r)
        cross = s2 + 16.0 * m.eps * (m.abs(s2) + r)
        qx = c0 + cross * (c1 + cross * c2)
        crossed = ok & (s2 <= r) & (cross <= r) & m.select(up, qx + w < 0, qx - w > 0)
        return free, m.select(ok, cand, -r), cross, crossed, up


def _root_after(m, a, b, c, after, r):
    """The smallest root > after of a s^2 + b s + c (stable form), or a
    value past r where there is none."""
    disc = b * b - 4.0 * a * c
    sq = m.sqrt(m.maximum(disc, 0.0))
    qq = -0.5 * (b + m.select(b >= 0, sq, -sq))
    big = 2.0 * r + 1.0
    s1 = m.select(a != 0, qq / m.select(a != 0, a, 1.0), -c / m.select(b != 0, b, 1.0))
    s2 = m.select(qq != 0, c / m.select(qq != 0, qq, 1.0), s1)
    real = (disc >= 0) | (a == 0)
    s1 = m.select(real & (m.abs(s1) < math.inf) & (s1 > after), s1, big)
    s2 = m.select(real & (m.abs(s2) < math.inf) & (s2 > after) & (a != 0), s2, big)
    return m.minimum(s1, s2)


def _ends(seg, q):
    """The quadratic's values at s = -r and +r, and the widening (R and the
    rounding) of any value of q over the segment."""
    pa = q.c0 - q.c1 * seg.r + q.c2 * seg.r2
    pb = q.c0 + q.c1 * seg.r + q.c2 * seg.r2
    return pa, pb, q.R + seg.slack(seg.mag(q))


def _finite_lo(m, v):
    return m.select(m.isnan(v), -math.inf, v)


def _finite_hi(m, v):
    return m.select(m.isnan(v), math.inf, v)


def _range(seg, q):
    m, r = seg.m, seg.r
    c0, c1, c2 = q.c0, q.c1, q.c2
    pa, pb, w = _ends(seg, q)
    lo, hi = m.minimum(pa, pb), m.maximum(pa, pb)
    inside = m.abs(c1) < 2.0 * m.abs(c2) * r
    c2s = m.select(c2 != 0, c2, 1.0)
    # c1 (c1 / c2) / 4, not c1^2 / (4 c2): c1^2 may underflow (f scaled by
    # 1e-30) or overflow where the quotient does not
    pv = c0 - 0.25 * c1 * (c1 / c2s)
    lo = m.select(inside & (c2 > 0), m.minimum(lo, pv), lo)
    hi = m.select(inside & (c2 < 0), m.maximum(hi, pv), hi)
    return iv.Interval(_finite_lo(m, lo - w), _finite_hi(m, hi + w))


def _add(seg, a, b, sign=1.0):
    c = [a.c0 + sign * b.c0, a.c1 + sign * b.c1, a.c2 + sign * b.c2]
    return Quad(*c, a.R + b.R + seg.slack(seg.mag(a) + seg.mag(b)))


def _scale(seg, k, a, k_err=None):
    """k a for a plain k (``k_err``: a bound of k's own rounding error)."""
    m = seg.m
    ka = m.abs(k)
    R = ka * a.R + seg.slack(ka * seg.mag(a))
    if k_err is not None:
        R = R + k_err * seg.mag(a)
    return Quad(k * a.c0, k * a.c1, k * a.c2, R)


def _mul(seg, a, b):
    m, r3, r4 = seg.m, seg.r3, seg.r4
    Ma, Mb = seg.mag(a), seg.mag(b)
    pa, pb = Ma - a.R, Mb - b.R           # bounds of the quadratic parts
    high = m.abs(a.c1 * b.c2 + a.c2 * b.c1) * r3 + m.abs(a.c2 * b.c2) * r4
    R = high + pa * b.R + pb * a.R + a.R * b.R + seg.slack(Ma * Mb)
    return Quad(a.c0 * b.c0, a.c0 * b.c1 + a.c1 * b.c0, a.c0 * b.c2 + a.c1 * b.c1 + a.c2 * b.c0, R)


def _pow(seg, a, n: int):
    return powi(a, n, lambda p, q: _mul(seg, p, q))


def _neg(a):
    return Quad(-a.c0, -a.c1, -a.c2, a.R)


def _select(m, c, a: Quad, b: Quad) -> Quad:
    return Quad(m.select(c, a.c0, b.c0), m.select(c, a.c1, b.c1), m.select(c, a.c2, b.c2),
                m.select(c, a.R, b.R))


def _via_interval(seg, n: Expr, ranges):
    """A constant form from the op's interval rule over the arguments'
    ranges (padded as in :func:`~lgshape.expr.evaluate_interval`)."""
    m = seg.m
    op = OPS[n.op]
    extra = (n.param,) if n.op == "pow" else ()
    r = op.interval(m, *ranges, *extra)
    if not op.exact:
        r = iv.pad(m, r, op.rounding, scale=float(n.param) if n.op == "pow" else 1.0)
    if op.nonneg:
        r = iv.nonneg(m, r)
    return from_interval(m, r)


def _chord(seg: Segment, op: str, a: Quad, b: Quad | None) -> Quad:
    """min(a, b), max(a, b) or |a| (b None) where neither side provably
    wins: with d = a - b over the segment in [dl, dh] (dl <= 0 <= dh),
    |d| lies between alpha d and the chord alpha d + beta through
    (dl, |dl|) and (dh, |dh|), so

        min(a, b) = (a + b) / 2 - |d| / 2  in  lam a + mu b - [0, beta / 2]

    (lam = (1 - alpha) / 2, mu = (1 + alpha) / 2; max: the sign of |d|
    and the two weights swap): a form that keeps the arguments' slopes
    where the interval rule gives a constant. Sound for the alpha
    computed: |d| - alpha d >= 0 for |alpha| <= 1, and it is convex in d,
    so its largest value over [dl, dh] is at an end (beta)."""
    m = seg.m
    d = a if b is None else _add(seg, a, b, -1.0)
    rd = _range(seg, d)
    dl, dh = m.minimum(rd.lo, 0.0), m.maximum(rd.hi, 0.0)
    den = dh - dl
    alpha = m.select(den > 0, (dh + dl) / m.select(den > 0, den, 1.0), 0.0)
    alpha = m.minimum(m.maximum(alpha, -1.0), 1.0)
    beta = m.maximum(-dl * (1.0 + alpha), dh * (1.0 - alpha)) * (1.0 + 4.0 * m.u)
    if b is None:
        # |a| in alpha a + [0, beta]
        base = _scale(seg, alpha, a)
        sign = 1.0
    else:
        lam, mu = 0.5 - 0.5 * alpha, 0.5 + 0.5 * alpha    # lam + mu = 1 to rounding
        wa, wb = (lam, mu) if op == "min" else (mu, lam)
        base = _add(seg, _scale(seg, wa, a, m.u), _scale(seg, wb, b, m.u))
        beta = 0.5 * beta
        sign = -1.0 if op == "min" else 1.0
    c0 = base.c0 + sign * 0.5 * beta
    R = base.R + 0.5 * beta * (1.0 + 4.0 * m.u) + seg.slack(m.abs(c0) + beta)
    bad = ~(m.abs(beta) < math.inf)
    inf = zero_like(c0) + math.inf
    return Quad(c0, base.c1, base.c2, m.select(bad, inf, R))


def _narrower(seg: Segment, t: Quad, fallback: Quad) -> Quad:
    """t unless its spread over the segment is over twice the constant
    form's (whose spread is its R)."""
    m = seg.m
    wide = m.abs(t.c1) * seg.r + m.abs(t.c2) * seg.r2 + t.R
    return _select(m, wide <= 2.0 * fallback.R, t, fallback)


def _smooth(seg: Segment, op: str, a: Quad) -> Quad:
    """sin, cos or exp of a form. With a = c0 + delta(s),
    f(c0 + delta) = f(c0) + f1 delta + f2 delta^2 / 2 + f3 delta^3 / 6
    (f1, f2 the derivatives at c0, f3 the third at a point between): its
    part of degree <= 2 in s is kept; the rest (the remainder's share of
    delta, the terms of delta^2 beyond c1^2 s^2, the cubic term with
    |f3| <= 1 for sin and cos, <= exp(c0 + |delta|) for exp) goes to R,
    with the error of the library's f (``m.eps_t``)."""
    m, r, r2 = seg.m, seg.r, seg.r2
    e2 = m.abs(a.c2) * r2 + a.R                 # |delta - c1 s|
    D = m.abs(a.c1) * r + e2                    # |delta|
    dd = 2.0 * m.abs(a.c1) * r * e2 + e2 * e2   # |delta^2 - c1^2 s^2|
    if op == "exp":
        f0 = m.exp(a.c0)
        f1 = f2 = f0
        # max exp over [c0 - D, c0 + D], from the end itself: f0 exp(D)
        # is 0 where f0 underflows and exp(c0 + D) does not (c0 = -95,
        # D = 18); the argument rounded up, the library's error added
        top = a.c0 + D
        M3 = m.exp(top + m.abs(top) * m.eps) * (1.0 + m.eps_t) + m.tiny
        # f0 = f1 = f2 within the library's error, or, where exp(c0)
        # underflows to 0 or a subnormal, within the smallest normal
        ef = m.eps_t * f0 + m.tiny
    else:
        s, c = m.sin(a.c0), m.cos(a.c0)
        f0, f1, f2 = (s, c, -s) if op == "sin" else (c, -s, -c)
        M3 = 1.0
        ef = 2.0 * m.eps_t
    c1 = f1 * a.c1
    c2 = f1 * a.c2 + 0.5 * f2 * (a.c1 * a.c1)
    R = m.abs(f1) * a.R + 0.5 * m.abs(f2) * dd + M3 * (D * D * D) * (1.0 / 6.0)
    R = R + ef * (1.0 + D + D * D)
    R = R * (1.0 + seg.g) + seg.slack(m.abs(f0) + m.abs(c1) * r + m.abs(c2) * r2)
    return Quad(f0, c1, c2, R)


#: min, max and abs compute the form of a mixed case (neither side
#: provably wins) in a branch a packet takes only where one of its lanes
#: needs it (:func:`_mixed`). Measured against False (one process,
#: interleaved, same hits; camera / incoherent / shadow rays): blobs
#: 1.10x / 1.09x / 1.10x; a sphere-and-box SDF union 1.22x / 1.11x / 1.26x.
BRANCH_MIXED = True


def _branch(seg: Segment, cond, form, R_else: float, label: str) -> Quad:
    """form() where ``cond``, in a branch that a packet takes only where one
    of its lanes needs it; the constant form 0 +- R_else elsewhere."""
    # (made before the branch: a value first made inside one lives there)
    z = zero_like(seg.r)
    other = (z, z, z, z + R_else)
    return Quad(*seg.m.branch(cond, lambda: _astuple(form()), lambda: other, label=label))


def _mixed(seg: Segment, cond, form) -> Quad:
    """form() where ``cond`` (an unknown form elsewhere, which the caller
    does not use there)."""
    if not BRANCH_MIXED:
        return form()
    return _branch(seg, cond, form, math.inf, "lgshape_quad_mixed")


def _exp_form(seg: Segment, n: Expr, a: Quad, ranges) -> Quad:
    """exp's form (:func:`_smooth` or its interval rule), computed in a
    branch that a packet takes only where one of its lanes' argument
    reaches :data:`~lgshape.expr.ops.EXP_FLOOR` on the segment; the
    constant form [0, EXP_TINY] elsewhere."""
    return _branch(seg, ~(ranges[0].hi < ops.EXP_FLOOR),
                   lambda: _narrower(seg, _smooth(seg, "exp", a), _via_interval(seg, n, ranges)),
                   ops.EXP_TINY, "lgshape_quad_exp")


def _astuple(q: Quad):
    return (q.c0, q.c1, q.c2, q.R)


def _node(seg: Segment, n: Expr, args, exact):
    """The form of node n from its arguments' (Quads or plain arrays);
    ``exact``: whether each argument's form is a polynomial's (no op that
    went through an interval rule below it)."""
    m = seg.m
    op = n.op
    quads = [isinstance(a, Quad) for a in args]
    if op == "mul" and not quads[0]:
        return _scale(seg, args[0], args[1], m.abs(args[0]) * m.eps + m.tiny)
    if op == "mul" and not quads[1]:
        return _scale(seg, args[1], args[0], m.abs(args[1]) * m.eps + m.tiny)
    if op == "div" and not quads[1]:
        k = 1.0 / args[1]
        return _scale(seg, k, args[0], m.abs(k) * m.eps + m.tiny)
    q = [a if isinstance(a, Quad) else _plain(m, a) for a in args]
    if op in ("add", "sub"):
        return _add(seg, q[0], q[1], 1.0 if op == "add" else -1.0)
    if op == "neg":
        return _neg(q[0])
    if op in ("mul", "pow"):
        t = _mul(seg, q[0], q[1]) if op == "mul" else _pow(seg, q[0], n.param)
        square = n.args[0] is n.args[1] if op == "mul" else n.param % 2 == 0
        if all(exact) or not square:
            return t
        # An argument from an interval rule is a constant form c0 +- R; its
        # square as a centred form c0^2 +- (2 |c0| R + R^2) loses the
        # dependency (the square of [2e-5, 6e-5] reached below 0), where
        # the interval rule is exact: take the rule where the form is
        # constant.
        flat = None
        for a in q:
            c = (a.c1 == 0) & (a.c2 == 0)
            flat = c if flat is None else flat & c
        ranges = []
        for a in q:
            w = a.R + seg.slack(m.abs(a.c0) + a.R)
            ranges.append(iv.Interval(m.select(m.isnan(w), -math.inf, a.c0 - w),
                                      m.select(m.isnan(w), math.inf, a.c0 + w)))
        return _select(m, flat, _via_interval(seg, n, ranges), t)
    ranges = [quad_range(seg, a) for a in q]
    if op in ("min", "max"):
        a_wins = (ranges[0].hi < ranges[1].lo) if op == "min" else (ranges[0].lo > ranges[1].hi)
        b_wins = (ranges[1].hi < ranges[0].lo) if op == "min" else (ranges[1].lo > ranges[0].hi)
        mixed = _mixed(seg, ~(a_wins | b_wins), lambda: _narrower(
            seg, _chord(seg, op, q[0], q[1]), _via_interval(seg, n, ranges)))
        return _select(m, a_wins, q[0], _select(m, b_wins, q[1], mixed))
    if op == "abs":
        mixed = _mixed(seg, (ranges[0].lo < 0) & (ranges[0].hi > 0), lambda: _narrower(
            seg, _chord(seg, op, q[0], None), _via_interval(seg, n, ranges)))
        return _select(m, ranges[0].lo >= 0, q[0], _select(m, ranges[0].hi <= 0, _neg(q[0]),
                                                            mixed))
    if op == "exp" and ops.NEGLIGIBLE_EXP:
        return _exp_form(seg, n, q[0], ranges)
    fallback = _via_interval(seg, n, ranges)
    if op in ("sin", "cos", "exp"):
        # the second-order rule unless it is over twice as wide as the
        # interval rule (a form composes better: products keep their
        # correlations)
        return _narrower(seg, _smooth(seg, op, q[0]), fallback)
    return fallback


_POLYNOMIAL = frozenset(("add", "sub", "mul", "neg", "pow"))


def _selection(n: Expr):
    """(c, x, y) where n is y + step(c) (x - y), else None: the derivative
    rule of min and max (:mod:`.ops`), the slope of the side that wins,
    x where c > 0 and y where c <= 0."""
    if n.op != "add":
        return None
    for y, p in (n.args, n.args[::-1]):
        if p.op != "mul":
            continue
        for s, dxy in (p.args, p.args[::-1]):
            if s.op == "step" and dxy.op == "sub" and dxy.args[1] is y:
                return s.args[0], dxy.args[0], y
    return None


def _selected(seg: Segment, c, x, y, form: Quad) -> Quad:
    """The form of y + step(c) (x - y) (``form``, from its ops) where c's
    sign is unknown on the segment; x's own form where c > 0 there, y's where
    c <= 0. Taken op by op, y + 1 (x - y) is x widened by twice y's
    remainder: the slope bound of a union took the remainder of every row
    that loses to an earlier one (a torus's, where a box won), and a ray
    grazing the box was split to widths of 1e-4 (capped at 4096)."""
    m = seg.m
    q = [v if isinstance(v, Quad) else _plain(m, v) for v in (c, x, y)]
    rc = quad_range(seg, q[0])
    return _select(m, rc.lo > 0, q[1], _select(m, rc.hi <= 0, q[2], form))


#: Bounds on the size of a quotient :func:`_norm_quotient` takes apart
#: (squares under the root, terms of the numerator, nodes of a product).
_NORM_MAX_SQUARES, _NORM_MAX_TERMS, _NORM_MAX_CHAIN = 8, 32, 32

_NORM_CACHE: dict = {}


def _norm_quotient(n: Expr):
    """(divisor constants, number of squares, terms) where n is
    A / (c sqrt(U)) with U = v_1^2 + ... + v_k^2 (each a product of a node
    by itself, or its square) and A a sum or difference of terms, each a
    product with one of the v_i as a factor: per term (i, the other
    factors); else None. The derivative rule of sqrt, A = U' (:mod:`.ops`),
    gives such quotients for every distance sqrt(v_1^2 + ... + v_k^2), with
    A = 2 v_1 v_1' + ... + 2 v_k v_k'. Nodes are interned (never freed), so
    the parse is kept by id."""
    hit = _NORM_CACHE.get(id(n))
    if hit is None:
        hit = _NORM_CACHE[id(n)] = (n, _parse_norm_quotient(n) if n.op == "div" else None)
    return hit[1]


def _parse_norm_quotient(n: Expr):
    A, D = n.args
    chain = product_chain(D, lambda e: e.op == "const", _NORM_MAX_CHAIN)
    if chain is None or len(chain[2]) != 1 or chain[2][0].op != "sqrt":
        return None
    dconsts = tuple(chain[1])
    index, stack = {}, [chain[2][0].args[0]]
    while stack:
        e = stack.pop()
        if e.op == "add":
            stack.extend(e.args)
            continue
        if e.op == "mul" and e.args[0] is e.args[1]:
            v = e.args[0]
        elif e.op == "pow" and e.param == 2:
            v = e.args[0]
        else:
            return None
        index.setdefault(id(v), len(index))
        if len(index) > _NORM_MAX_SQUARES:
            return None
    terms, stack = [], [A]
    while stack:
        e = stack.pop()
        if e.op in ("add", "sub"):
            stack.extend(e.args)
            continue
        if e.op == "neg":
            stack.append(e.args[0])
            continue
        # the term as +-(f_1 f_2 ...), constants among the factors
        chain = product_chain(e, lambda _: False, _NORM_MAX_CHAIN)
        if chain is None:
            return None
        factors = chain[2]
        j = next((j for j, f in enumerate(factors) if id(f) in index), None)
        if j is None or len(terms) == _NORM_MAX_TERMS:
            return None
        terms.append((index[id(factors[j])], tuple(factors[:j] + factors[j + 1:])))
    return dconsts, len(index), tuple(terms)


def _norm_bound(seg: Segment, parsed, memo, form: Quad) -> Quad:
    """The form of A / (c sqrt(U)) (:func:`_norm_quotient`; ``form``, from
    the op's rule) where that is not finite (U's range reaches 0: a ray
    along a box's face, where max(q, 0) = 0 or q's sign is unknown to
    rounding): the constant form 0 +- B, B = |X| / |c| rounded up, with

        |A| / (|c| sqrt(U)) <= sum_i |v_i| X_i / (|c| |v|) <= |X| / |c|

    (v the distinct v_i, sqrt(U) >= |v|; Cauchy-Schwarz), X_i the sum over
    v_i's terms of the product of the magnitudes of their other factors
    (from those factors' forms' ranges, which hold at every point of the
    segment). That holds wherever the quotient is defined (U > 0), an
    algebraic fact of the structure. For A = U' (the slope of a distance
    |v| = sqrt(U) along the ray) it bounds that slope where U > 0, and where
    U = 0 |v| is at its minimum 0, so its slope there (where it has one) is
    0: |v| is B-Lipschitz on the segment, and the mean-value form over it
    stays sound across the points where U = 0. The op's rule is unbounded
    wherever U's range reaches 0 (as the slope of sqrt u is): a ray with a
    zero (or 1e-8) direction component along a box's face, where F is
    constant to rounding, had no slope bound there (no mean-value form, no
    monotonicity) and was split down to the minimum width all along the
    face (4096 iterations). Where the op's form is finite it is kept."""
    m = seg.m
    dconsts, k, terms = parsed
    # (the op's rule gives R = inf where it has no finite bound)
    bad = ~(form.R < math.inf)

    def mag(node):
        v = memo[id(node)]
        r = quad_range(seg, v if isinstance(v, Quad) else _plain(m, v))
        return m.maximum(m.abs(r.lo), m.abs(r.hi))

    def bound():
        X = [None] * k
        ops_ = 0                    # roundings, each at most u / 2 relative
        for i, others in terms:
            p = None
            for f in others:
                a = mag(f)
                p = a if p is None else p * a
            p = zero_like(seg.r) + 1.0 if p is None else p
            X[i] = p if X[i] is None else X[i] + p
            ops_ += len(others)
        X = [zero_like(seg.r) if x is None else x for x in X]
        if k == 1:
            B = X[0]
        else:
            # |X| = M sqrt(sum (X_i / M)^2), M = max X_i: no under- or
            # overflow of the squares
            M = X[0]
            for x in X[1:]:
                M = m.maximum(M, x)
            Ms = m.select(M > 0, M, 1.0)
            s = None
            for x in X:
                q = x / Ms
                s = q * q if s is None else s + q * q
            B = m.select(M < math.inf, M * m.sqrt(s + k * m.tiny), math.inf)
            B = m.select(M > 0, B, 0.0)
            ops_ += 4 * k + 2
        C = None                    # |c|, rounded down
        for c in dconsts:
            a = m.abs(memo[id(c)])
            C = a if C is None else C * a
        if C is not None:
            ops_ += 2 * len(dconsts)
            C = C * (1.0 - (len(dconsts) + 1) * m.u)
            B = m.select(C > 0, B / m.select(C > 0, C, 1.0), math.inf)
        B = B * (1.0 + (ops_ + 2) * m.u) + m.tiny
        z = zero_like(B)
        return Quad(z, z, z, m.select(m.isnan(B), math.inf, B))
    new = _mixed(seg, bad, bound)
    return _select(m, bad, new, form)


def evaluate_quadratic(roots, env: dict, seg: Segment, memo=None):
    """Quadratic forms of ``roots`` (an Expr or a list) over the segment.

    ``env`` maps variable names to :class:`Quad` (the coordinates, see
    :func:`coordinate`), :class:`~lgshape.interval.Interval` (parameters
    known to a range) or plain arrays (exact values such as the direction).
    A node whose arguments are all plain stays plain. Returns Quads.
    ``memo``: a dict that keeps the nodes' forms for a later call on the
    same segment (which then computes only the nodes not yet in it)."""
    single = isinstance(roots, Expr)
    roots = [roots] if single else list(roots)
    m = seg.m
    if memo is None:
        memo = {}
    # nodes whose form went through an interval rule
    inexact = memo.setdefault("inexact", set())
    with m.errstate():
        for n in topological(roots):
            if id(n) in memo:
                continue
            if n.op in ("const", "named"):
                memo[id(n)] = constant(n, m)
                continue
            if n.op == "var":
                v = _lookup(env, n.param)
                if isinstance(v, iv.Interval):
                    v = from_interval(m, v)
                    inexact.add(id(n))
                memo[id(n)] = v
                continue
            args = [memo[id(a)] for a in n.args]
            if not any(isinstance(a, Quad) for a in args):
                extra = (n.param,) if n.op == "pow" else ()
                memo[id(n)] = OPS[n.op].value(m, *args, *extra)
                continue
            exact = [id(a) not in inexact for a in n.args]
            memo[id(n)] = _node(seg, n, args, exact)
            sel = _selection(n)
            if sel is not None:
                memo[id(n)] = _selected(seg, *(memo[id(v)] for v in sel), memo[id(n)])
            quo = _norm_quotient(n)
            if quo is not None:
                memo[id(n)] = _norm_bound(seg, quo, memo, memo[id(n)])
            if n.op not in _POLYNOMIAL or not all(exact):
                inexact.add(id(n))
    out = [memo[id(r)] if isinstance(memo[id(r)], Quad) else _plain(m, memo[id(r)])
           for r in roots]
    return out[0] if single else out
