"""Interval arithmetic on numpy or Dr.Jit arrays.

Contract: for every op, the result ``[lo, hi]`` contains every value the
op takes, in exact arithmetic, at the points of its input intervals where it
is *defined* (not NaN). Where f is NaN there is no surface (see
:mod:`lgshape.trace`), so values at undefined points need no enclosing: sqrt
and log of an interval reaching below 0 enclose the defined part
(``sqrt([-1, 4]) = [0, 2]``), and an op defined nowhere on its input returns
the empty interval ``[+inf, -inf]``. Every op is undefined where an argument
is (NaN propagates through every value rule, min and max included), so the
evaluators make a node empty wherever an argument is (:func:`is_empty`),
and an f undefined on a whole region has an empty interval there: the
region is excluded. The derivative of
such an op is unbounded at the domain's edge (``1 / (2 sqrt u)`` with u
reaching 0), so a mean-value bound is never taken across an undefined gap.

After each op the bounds are padded outward to cover rounding (the rounding
mode is not directed): ``eps * |bound| + tiny`` for correctly rounded ops,
``eps_t * |bound| + tiny`` for exp, ``eps_t * (|bound| + 1)`` for sin, cos and
log (their absolute error does not scale with the result), and ``n * eps`` for
an integer power by n multiplications; see :mod:`lgshape.arraymath` for the
values. Ops whose results are never negative (sqrt, exp, even powers) are
clamped at 0 after padding. A NaN bound (from ``inf - inf``, ``0 * inf``) is
turned into an infinite one in :func:`pad`, so a NaN never narrows a result;
a lower bound of +inf (overflow of a positive value, or an empty interval)
stays +inf and an upper bound of -inf stays -inf: overflow is rounded to
nearest, so the exact value lies beyond the largest float. Division by an
interval that contains 0 gives infinite bounds.

Ops whose rule only selects among input bounds (neg, abs, min, max) are
exact and skip the padding (``Op.rounding == "exact"`` in the op table).

Operands of the rules may be intervals or plain arrays (a degenerate interval,
e.g. the ray direction); :func:`promote` makes an interval of a plain value.
"""
from __future__ import annotations

import math

from .arraymath import powi


class Interval:
    __slots__ = ("lo", "hi")

    def __init__(self, lo, hi):
        self.lo, self.hi = lo, hi

    def __repr__(self):
        return f"Interval({self.lo}, {self.hi})"

    def contains_zero(self):
        return (self.lo <= 0) & (self.hi >= 0)


def magnitude(m, a: Interval):
    """max |v| over the interval a."""
    return m.maximum(m.abs(a.lo), m.abs(a.hi))


def pad(m, r: Interval, rounding: str = "rounded", scale: float = 1.0) -> Interval:
    """Widen r outward by the rounding error of one op of the given kind
    (``"rounded"``, ``"relative_t"``, ``"absolute_t"``); ``scale`` multiplies
    the relative part (an integer power's number of roundings)."""
    eps = (m.eps_t if rounding != "rounded" else m.eps) * scale
    slack = m.tiny + (eps if rounding == "absolute_t" else 0.0)
    lo = m.select(r.lo == math.inf, r.lo, r.lo - (m.abs(r.lo) * eps + slack))
    hi = m.select(r.hi == -math.inf, r.hi, r.hi + (m.abs(r.hi) * eps + slack))
    lo = m.select(m.isnan(lo), -math.inf, lo)
    hi = m.select(m.isnan(hi), math.inf, hi)
    return Interval(lo, hi)


def nonneg(m, r: Interval) -> Interval:
    """Clamp the lower bound of a never-negative op's result at 0."""
    return Interval(m.maximum(r.lo, 0.0), r.hi)


def promote(m, v) -> Interval:
    if isinstance(v, Interval):
        return v
    return pad(m, Interval(v, v))


def is_empty(m, r: Interval):
    """True where r is empty (lo > hi: an op defined nowhere on its input)."""
    return r.lo > r.hi


def emptied(m, r: Interval, empty) -> Interval:
    """r, made empty where ``empty`` holds."""
    return Interval(m.select(empty, math.inf, r.lo), m.select(empty, -math.inf, r.hi))


def i_add(m, a, b):
    return Interval(a.lo + b.lo, a.hi + b.hi)


def i_sub(m, a, b):
    return Interval(a.lo - b.hi, a.hi - b.lo)


def i_neg(m, a):
    return Interval(-a.hi, -a.lo)


def i_mul(m, a, b):
    p1, p2, p3, p4 = a.lo * b.lo, a.lo * b.hi, a.hi * b.lo, a.hi * b.hi
    mn, mx = m.minimum, m.maximum
    # 0 * inf is NaN; there the product's limit is 0, which the other
    # products' hull (or pad()) already covers.
    return Interval(mn(mn(p1, p2), mn(p3, p4)), mx(mx(p1, p2), mx(p3, p4)))


def i_scale(m, s, a):
    """plain s times interval a (2 products instead of 4)."""
    p, q = s * a.lo, s * a.hi
    return Interval(m.minimum(p, q), m.maximum(p, q))


def i_div(m, a, b):
    zero_in = (b.lo <= 0) & (b.hi >= 0)
    r = i_mul(m, a, Interval(1.0 / b.hi, 1.0 / b.lo))
    return Interval(m.select(zero_in, -math.inf, r.lo), m.select(zero_in, math.inf, r.hi))


def i_pow(m, a, n: int):
    pl, ph = powi(a.lo, n), powi(a.hi, n)
    if n % 2:
        return Interval(pl, ph)
    lo = m.select(a.lo >= 0, pl, m.select(a.hi <= 0, ph, 0.0))
    hi = m.select(a.lo >= 0, ph, m.select(a.hi <= 0, pl, m.maximum(pl, ph)))
    return Interval(lo, hi)


def i_sqrt(m, a):
    """sqrt over the defined part of a; empty where a < 0 throughout."""
    return emptied(m, Interval(m.sqrt(m.maximum(a.lo, 0.0)), m.sqrt(m.maximum(a.hi, 0.0))),
                   a.hi < 0)


def i_exp(m, a):
    return Interval(m.exp(a.lo), m.exp(a.hi))


def i_log(m, a):
    """log over the defined part of a (log 0 = -inf); empty where a < 0
    throughout."""
    return emptied(m, Interval(m.log(m.maximum(a.lo, 0.0)), m.log(m.maximum(a.hi, 0.0))),
                   a.hi < 0)


def _periodic(m, a, f, peak: float):
    """Range of a 2*pi periodic f with maximum 1 at ``peak`` and minimum -1
    half a period later."""
    two_pi = 2.0 * math.pi
    fl, fh = f(a.lo), f(a.hi)
    lo, hi = m.minimum(fl, fh), m.maximum(fl, fh)
    k_max = m.ceil((a.lo - peak) / two_pi)
    k_min = m.ceil((a.lo - peak - math.pi) / two_pi)
    has_max = peak + two_pi * k_max <= a.hi
    has_min = peak + math.pi + two_pi * k_min <= a.hi
    wide = ~((a.hi - a.lo) < two_pi)        # also true for NaN / inf widths
    hi = m.select(has_max | wide, 1.0, hi)
    lo = m.select(has_min | wide, -1.0, lo)
    return Interval(lo, hi)


def i_sin(m, a):
    return _periodic(m, a, m.sin, 0.5 * math.pi)


def i_cos(m, a):
    return _periodic(m, a, m.cos, 0.0)


def i_abs(m, a):
    lo = m.select(a.lo >= 0, a.lo, m.select(a.hi <= 0, -a.hi, 0.0))
    hi = m.maximum(m.abs(a.lo), m.abs(a.hi))
    return Interval(lo, hi)


def i_min(m, a, b):
    return Interval(m.minimum(a.lo, b.lo), m.minimum(a.hi, b.hi))


def i_max(m, a, b):
    return Interval(m.maximum(a.lo, b.lo), m.maximum(a.hi, b.hi))


def i_step(m, a):
    return Interval(m.select(a.lo > 0, 1.0, 0.0), m.select(a.hi > 0, 1.0, 0.0))


def i_kink(m, a):
    zero_in = ~((a.lo > 0) | (a.hi < 0))
    return Interval(m.select(zero_in, -math.inf, 0.0), m.select(zero_in, math.inf, 0.0))
