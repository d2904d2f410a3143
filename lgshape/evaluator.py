"""F, g and their bounds along rays: the evaluator of the guaranteed search
(:mod:`lgshape.search`) for one :class:`~lgshape.trace.Surface` and backend.

For each ray, F(t) = f(o + t d), g = dF/dt, h = d^2F/dt^2 (exact symbolic
derivatives). :class:`Evaluator` gives F's and g's point values and their
bounds over a ray interval, and :meth:`Evaluator.test` the Kalra-Barr test
of one interval (:class:`IntervalTest`): with midpoint t_m and half width r,

- *exclusion*: the enclosure of F over the interval has one sign -> no root;
- *monotonicity*: g keeps one sign on the interval -> at most one root; the
  signs of F at the ends decide whether it has one, and in which half;
- otherwise the search splits it.

The bounds come from one of the search modes
(:data:`lgshape.trace.SEARCH_MODES`): ``"interval"`` bounds F and g over the
interval by quadratic forms along the ray (:mod:`lgshape.expr.quadratic`:
exact on square sums, third order on polynomials; for a polynomial f, or a
sum of sinusoids, from each ray's coefficients, :mod:`lgshape.expr.raypoly`
and :mod:`lgshape.expr.raytrig`), and F also by the mean-value form
F(t_m) + [g] [-r, r]; ``"taylor"`` and ``"global"`` are the seed's test
|g(t_m)| > G r with G >= |h| local to the interval or global (plus F in
F(t_m) +- |g(t_m)| r + [h] r^2/2). A table form (many primitives,
:mod:`lgshape.tables`) evaluates the rows of the current cell only.

**Point values** of F and g are evaluated in float64 with a running error
bound per value (:mod:`lgshape.pointerror`): the bound is relative to the
magnitudes actually evaluated along that ray, never a fixed absolute floor,
so the hits of k * f are those of f for any k that float32 intervals hold.
Signs are decided only outside that bound, so rounding noise never decides
one. Where the interval forms alone decide an interval (F's range excludes
0; or, for an f defined everywhere, g keeps one sign and F's signs at the
ends are known), no point value is taken (:data:`FORM_DECIDES`).

**Interval values** of F and g over a ray interval are the ranges of
float32 quadratic forms along the ray (which fall back on the interval
rules of :mod:`lgshape.interval` for the ops that are not polynomial); F
over an interval is the intersection of that range and the mean-value form
where those are finite, else (where F(t_m) is undefined or its derivative
unbounded: domain edges, poles) the natural interval form.

**Coordinates.** Each ray is moved to its box entry in float64
(:func:`prepare_rays`), and f is evaluated in coordinates local to the box
centre (:mod:`lgshape.expr.shift`; a table form's rows about their table's
centre, :func:`lgshape.tables.localize_template`), so geometry far from the
origin is solved to the same relative accuracy as near it. The search's
parameter s is the distance from the entry in units of the direction.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr

from . import bounds, grid as gridmod
from . import interval as iv
from .expr import evaluate, evaluate_with_error, raypoly, raytrig
from .expr.quadratic import (Segment, evaluate_quadratic, quad_clip, quad_ends, quad_env,
                             quad_range)

#: On the expression path, no point value of F where F's quadratic forms
#: decide the interval alone (:meth:`Evaluator._decided`); a packet skips
#: the point's evaluation when none of its lanes needs it. False evaluates
#: F at every tested interval's middle (for comparison; docs/kernel-plan.md
#: gives the measurements of this and the search's other switches).
FORM_DECIDES = True


@dataclass
class Rays:
    """The per-ray constants of one search: the ray moved to its box entry
    in the box's local coordinates, u(s) = e + s d for s in [0, span], and
    the widths that scale with the ray's speed."""
    e64: list            # entry point, float64
    d64: list            # direction, float64
    e32: list            # the same in float32 (intervals)
    d32: list
    g_org: list          # entry point relative to the grid's lower corner
    span: object         # Float: length of the segment in the box, in s
    s_max: object        # Float: the query's t_max in s (rounded up; inf: none)
    s_max64: object      # Float64: the same, unrounded
    margin: object       # Float: overlap of neighbouring cell segments
    cell_len: object     # Float: the smallest cell's edge, in s
    r_min: object        # Float: minimum half width of a search interval
    tol: object          # Float64: refinement tolerance in s
    entering: object     # Bool: the ray enters the box from outside (the walk's tables)


class Evaluator:
    """F, g and their bounds along the rays for one Surface and backend:
    point values in float64 with error bounds, float32 intervals over
    segments, and the Kalra-Barr test of one interval (:meth:`test`)."""

    def __init__(self, surf, K, rays: Rays):
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
        R, u = self.rays, self.K.m64.u
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
                F = dr.select(known, F, Float64(c0))
            return (F, eF, dr.select(flat, g, Float64(c1)), None, decided), B, \
                dr.select(flat, 0.0, Float64(c2))
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
        m64 = self.K.m64
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
        Float64 = m64.Float
        # (every value as a Float64: a constant f, or a constant g, is an
        # opaque scalar with the Python error 0.0, which a branch's state
        # may not mix with arrays)
        if self.mode == "interval":
            # g's point value only steers Newton: no error bound needed.
            def F_at(s):
                F, eF = evaluate_with_error(self.f, env, err, m64)
                return Float64(F), Float64(eF)

            def g_at(s):
                return Float64(evaluate(self.ge, env, m64))
            if where is None:
                F, eF = F_at(s)
            else:
                F, eF = dr.if_stmt(args=(s,), cond=where, true_fn=F_at,
                                   false_fn=lambda s: (Float64(0), Float64(0)),
                                   label="lgshape_point")
            if g_where is None:
                return F, eF, g_at(s), None
            g = dr.if_stmt(args=(s,), cond=g_where, true_fn=g_at,
                           false_fn=lambda s: Float64(0), label="lgshape_slope")
            return F, eF, g, None
        (F, eF), (g, eg) = evaluate_with_error([self.f, self.ge], env, err, m64)
        return Float64(F), Float64(eF), Float64(g), Float64(eg)

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
        K, R = self.K, self.rays
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
        K, R = self.K, self.rays
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
        K, R = self.K, self.rays
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
        :meth:`point_and_bounds`. See :class:`IntervalTest`."""
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
            # (Evaluator._decided): no root, or one in the whole interval
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
        return IntervalTest(
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
class IntervalTest:
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
    Float64 = dr.float64_array_t(type(lo))
    return type(lo)(0.5 * (Float64(hi) - Float64(lo))) * (1 + 2.0**-22)


def _end_offset(lo, hi):
    """How far from the middle tm = (lo + hi) / 2 (float64) the test takes
    F's signs at the ends of [lo, hi] (float32): the half width, a little
    less, so that tm -+ it lies inside [lo, hi]. (The half width r that the
    enclosures cover is rounded up instead, past the ends; a sign taken
    there, say at tm - r before lo, is not F's at lo: on the first interval
    of a ray leaving the surface it would see the root just behind the
    origin, and bracket [lo, tm] with no root in it.)"""
    Float64 = dr.float64_array_t(type(lo))
    return 0.5 * (Float64(hi) - Float64(lo)) * (1 - 2.0**-50)


def _sign_of(lo, hi):
    """+1 / -1 where [lo, hi] has one strict sign, else 0 (NaN: 0)."""
    return dr.select(lo > 0, 1, dr.select(hi < 0, -1, 0))


def _either_sign(s1, s2):
    """The sign two bounds tell (0 where neither does, or they disagree)."""
    return dr.select(s1 == 0, s2, dr.select((s2 != 0) & (s2 != s1), 0, s1))


def sign_known(F, eF):
    """Sign of a point value outside its error bound; 0 where it cannot be
    told from 0; 2 where F is undefined (NaN or infinite) or its error bound
    overflows (the value cannot be trusted)."""
    return dr.select(dr.isfinite(F) & dr.isfinite(eF), _sign_of(F - eF, F + eF), 2)


def _down(v):
    """One float64 rounding of a sum, covered outward."""
    return v - (dr.abs(v) * 2.0**-51 + 2.0**-1020)


def _up(v):
    return v + (dr.abs(v) * 2.0**-51 + 2.0**-1020)


def _up32(v):
    """A Float64 v >= 0 as a float32 at least v (inf stays inf)."""
    return dr.float32_array_t(type(v))(v * (1.0 + 2.0**-22))

def prepare_rays(K, o, d, t_min, t_max, active, n):
    """Checked rays, clipped to the box in float64 and moved to its entry:
    (active, t_start, Rays)."""
    Float, Float64 = K.m.Float, K.m64.Float
    Bool = dr.mask_t(Float)
    o64 = [Float64(o[i]) for i in range(3)]
    d64 = [Float64(d[i]) for i in range(3)]
    ok_dir = dr.isfinite(d64[0]) & dr.isfinite(d64[1]) & dr.isfinite(d64[2]) \
        & (d64[0] * d64[0] + d64[1] * d64[1] + d64[2] * d64[2] > 0) \
        & ~(dr.isnan(o64[0]) | dr.isnan(o64[1]) | dr.isnan(o64[2]))
    # the segment searched is the ray's in the box from t_min on, whatever
    # t_max: t_max only drops the roots past it (see Rays.s_max), so the
    # bisection tree, and the first root, do not depend on it
    t_start, t_exit = gridmod.clip_to_box(o64, d64, K.lo, K.hi, Float64(t_min), math.inf)
    t_max64 = Float64(t_max)
    t_end = dr.minimum(t_exit, t_max64)
    active = (Bool(active) | dr.zeros(Bool, n)) & ok_dir & (t_start <= t_end) \
        & dr.isfinite(t_start) & dr.isfinite(t_end)
    entering = active & (t_start > Float64(t_min))
    t_start = dr.select(active, t_start, 0.0)
    s_max64 = dr.select(active & (t_max64 < t_exit), t_max64 - t_start, math.inf)
    e64 = [dr.select(active, o64[i] - K.centre[i] + t_start * d64[i], 0.0) for i in range(3)]
    d32 = [Float(dr.select(active, d[i], 0.0)) for i in range(3)]
    dlen = dr.sqrt(d32[0] * d32[0] + d32[1] * d32[1] + d32[2] * d32[2])
    dlen = dr.select(dlen > 0, dlen, 1.0)
    cell = dr.minimum(dr.minimum(K.grid.cell[0], K.grid.cell[1]), K.grid.cell[2])
    rays = Rays(
        e64=e64, d64=d64, e32=[Float(v) for v in e64], d32=d32,
        g_org=[Float(e64[i] + K.grid_origin[i]) for i in range(3)],
        span=Float(dr.select(active, t_exit - t_start, 0.0)),
        s_max=_up32(s_max64), s_max64=s_max64,
        margin=1e-3 * cell / dlen,
        cell_len=cell / dlen,
        r_min=1e-6 * K.diag / dlen,
        tol=Float64(1e-6 * K.diag / dlen),
        entering=entering)
    return active, t_start, rays


@dataclass
class KernelData:
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


def table_point(K, p, with_gradient=False):
    """f (and grad f) of a table form at points p, over the rows of the cell
    each point lies in (every row where it lies in no occupied cell)."""
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

