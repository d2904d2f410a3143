"""Running error bounds for point values (forward error analysis).

A point value of f computed in floating point differs from the exact value
of f at the same (exact) input by its rounding error. Each rule here bounds
that error for one op: given the computed arguments ``a``, their error bounds
``ea`` (absolute) and the computed result ``v``, it returns ``e`` with
|exact op(exact args) - v| <= e. The bounds are relative to the magnitudes
actually evaluated (no fixed absolute floor, so k * f has k times the error
bound of f for any k; exp's, whose result may underflow, adds the smallest
normal number ``m.tiny`` times its growth over the argument's error), and
they are evaluated together with the values, so each ray point gets its own
bound. Unit roundoff ``m.u`` covers one correctly rounded op (+ - * / sqrt,
with margin); ``m.eps_t`` covers the library's exp, log, sin and cos (64
ulp in float64). The error of computing
``e`` itself is absorbed by a final factor (:data:`SAFETY`).

Where an argument's error can reach a singularity of the op (a divisor within
its error of 0, a log argument within its error of 0), the bound is +inf: the
value cannot be trusted there, and callers treat it as unknown. Where the
computed value is NaN the bound is NaN: f is undefined at that point (no
surface). ``step`` (the derivative of abs/min/max) has error 1 where its
argument cannot be told from 0; ``kink`` (a Dirac measure) is 0 as a value.
"""
from __future__ import annotations

from .arraymath import powi, zero_like

SAFETY = 1.0 + 2.0 ** -40     # covers the rounding of the error computation


def e_add(m, v, a, b, ea, eb):
    return ea + eb + m.u * m.abs(v)


def e_mul(m, v, a, b, ea, eb):
    return m.abs(a) * eb + m.abs(b) * ea + ea * eb + m.u * m.abs(v)


def e_div(m, v, a, b, ea, eb):
    # |a*/b* - a/b| <= (|b| ea + |a| eb) / (|b| (|b| - eb)) for |b| > eb
    room = m.abs(b) - eb
    e = (ea + m.abs(v) * (1.0 + 2.0 * m.u) * eb) / room + m.u * m.abs(v)
    return m.select(room > 0, e, m.inf)


def e_same(m, v, a, ea):
    """neg, abs: exact ops, the argument's error passes through."""
    return ea


def e_minmax(m, v, a, b, ea, eb):
    return m.maximum(ea, eb)


def e_pow(m, v, a, ea, n: int):
    # binary exponentiation: at most 2 log2(n) roundings, whose relative
    # errors compound to below 2 n u; the argument's error: (|a| + ea)^n - |a|^n
    # <= n ea |a|^(n-1) (1 + n ea / |a|) while n ea <= |a| / 2.
    aa = m.abs(a)
    small = n * ea < 0.5 * aa
    rel = n * ea / m.select(small, aa, 1.0)
    e_small = m.abs(v) * (rel * (1.0 + rel) + 2.0 * n * m.u)
    e_large = 2.0 * powi(aa + ea, n) * (1.0 + 4.0 * n * m.u)
    return m.select(small, e_small, e_large)


def e_sqrt(m, v, a, ea):
    # |sqrt(p) - sqrt(q)| <= min(|p - q| / sqrt(q), sqrt(|p - q|))
    via_slope = ea / m.select(v > 0, v, 1.0)
    e = m.select(v > 0, m.minimum(via_slope, m.sqrt(ea)), m.sqrt(ea))
    return e * (1.0 + 4.0 * m.u) + m.u * v


def e_exp(m, v, a, ea):
    # exp(a + ea) - exp(a) = exp(a) (exp(ea) - 1), exp(ea) - 1 <= ea (1 + ea) for ea <= 1;
    # where exp(a) underflows (0 or a subnormal: exp(a) below the smallest
    # normal), the exact exp(a + ea) <= tiny exp(ea) <= tiny (1 + grow)
    grow = m.select(ea <= 1.0, ea * (1.0 + ea), m.exp(ea))
    return v * (1.0 + m.eps_t) * grow + m.eps_t * v + m.tiny * (1.0 + grow)


def e_log(m, v, a, ea):
    # log(a) - log(a - ea) = log(1 + ea / (a - ea)) <= ea / (a - ea)
    room = a - ea
    e = ea / room + m.eps_t * m.abs(v) + 4.0 * m.u
    return m.select(room > 0, e, m.inf)


def e_periodic(m, v, a, ea):
    """sin, cos: Lipschitz 1; absolute library error, plus argument
    reduction growing with |a|."""
    return m.minimum(ea, 2.0) + m.eps_t + 2.0 * m.u * m.abs(a)


def e_step(m, v, a, ea):
    return m.select(m.abs(a) > ea, 0.0, 1.0) + zero_like(v)


def e_zero(m, v, a, ea):
    return zero_like(v)
