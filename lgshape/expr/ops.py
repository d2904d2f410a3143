"""The op table: the single source of truth for every operation.

Each row gives an op's arity, its value rule (over an array namespace ``m``,
see :mod:`lgshape.arraymath`), its derivative rule (symbolic, forward mode:
the derivative of the node given its arguments and their derivatives, as an
expression), its interval rule and padding (see :mod:`lgshape.interval`) and
its point-error rule (see :mod:`lgshape.pointerror`). The parser's
function names, the evaluators and the shared tests all read this table:
adding an op is one row.

``step`` and ``kink`` are internal: they appear only in derivatives of the
non-smooth ops (abs, min, max). ``step(c)`` is 1 where c > 0, else 0;
``kink(c)`` is its derivative, 0 as a value but with the interval
[-inf, inf] wherever c may vanish, so that a bound on a second derivative
stays sound across a crease (where the true derivative is a Dirac delta).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

from .. import interval as iv
from .. import pointerror as pe
from ..arraymath import powi, zero_like
from . import node as N


@dataclass(frozen=True)
class Op:
    name: str
    arity: int
    value: Callable           # value(m, *args[, param])
    deriv: Callable           # deriv(node, args, dargs) -> Expr
    interval: Callable        # interval(m, *intervals[, param]) -> Interval
    error: Callable           # error(m, v, *args, *arg_errors[, param]) -> bound (pointerror)
    rounding: str = "rounded"  # interval padding: exact | rounded | relative_t | absolute_t
    public: bool = True       # callable by name in the expression language
    nonneg: bool = False      # results are never negative (clamp padded intervals at 0)

    @property
    def exact(self) -> bool:
        """The interval rule's bounds are exact (no rounding, no NaN)."""
        return self.rounding == "exact"


def _d_div(e, args, d):
    a, b = args
    return N.div(N.sub(d[0], N.mul(e, d[1])), b)


def _d_pow(e, args, d):
    n = e.param
    return N.mul(N.mul(float(n), N.power(args[0], n - 1)), d[0])


_TABLE = [
    Op("add", 2, lambda m, a, b: a + b, lambda e, a, d: N.add(d[0], d[1]), iv.i_add, pe.e_add),
    Op("sub", 2, lambda m, a, b: a - b, lambda e, a, d: N.sub(d[0], d[1]), iv.i_sub, pe.e_add),
    Op("mul", 2, lambda m, a, b: a * b,
       lambda e, a, d: N.add(N.mul(d[0], a[1]), N.mul(a[0], d[1])), iv.i_mul, pe.e_mul),
    Op("div", 2, lambda m, a, b: a / b, _d_div, iv.i_div, pe.e_div),
    Op("neg", 1, lambda m, a: -a, lambda e, a, d: N.neg(d[0]), iv.i_neg, pe.e_same,
       rounding="exact"),
    Op("pow", 1, lambda m, a, n: powi(a, n), _d_pow, iv.i_pow, pe.e_pow),
    Op("sqrt", 1, lambda m, a: m.sqrt(a),
       lambda e, a, d: N.div(d[0], N.mul(2.0, e)), iv.i_sqrt, pe.e_sqrt, nonneg=True),
    Op("exp", 1, lambda m, a: m.exp(a), lambda e, a, d: N.mul(e, d[0]), iv.i_exp, pe.e_exp,
       rounding="relative_t", nonneg=True),
    Op("log", 1, lambda m, a: m.log(a), lambda e, a, d: N.div(d[0], a[0]), iv.i_log, pe.e_log,
       rounding="absolute_t"),
    Op("sin", 1, lambda m, a: m.sin(a), lambda e, a, d: N.mul(N.cos(a[0]), d[0]),
       iv.i_sin, pe.e_periodic, rounding="absolute_t"),
    Op("cos", 1, lambda m, a: m.cos(a), lambda e, a, d: N.neg(N.mul(N.sin(a[0]), d[0])),
       iv.i_cos, pe.e_periodic, rounding="absolute_t"),
    Op("abs", 1, lambda m, a: m.abs(a),
       lambda e, a, d: N.mul(N.sub(N.mul(2.0, N.step(a[0])), 1.0), d[0]), iv.i_abs, pe.e_same,
       rounding="exact"),
    Op("min", 2, lambda m, a, b: m.minimum(a, b),
       lambda e, a, d: N.add(d[1], N.mul(N.step(N.sub(a[1], a[0])), N.sub(d[0], d[1]))),
       iv.i_min, pe.e_minmax, rounding="exact"),
    Op("max", 2, lambda m, a, b: m.maximum(a, b),
       lambda e, a, d: N.add(d[1], N.mul(N.step(N.sub(a[0], a[1])), N.sub(d[0], d[1]))),
       iv.i_max, pe.e_minmax, rounding="exact"),
    Op("step", 1, lambda m, a: m.select(a > 0, 1.0, 0.0) + zero_like(a),
       lambda e, a, d: N.kink(a[0]), iv.i_step, pe.e_step, public=False, rounding="exact"),
    Op("kink", 1, lambda m, a: zero_like(a), lambda e, a, d: N.ZERO, iv.i_kink, pe.e_zero,
       public=False, rounding="exact"),
]

OPS: dict[str, Op] = {op.name: op for op in _TABLE}

#: Functions callable by name in the expression language, with their arity
#: (min and max take two or more arguments).
FUNCTIONS = {op.name: op.arity for op in _TABLE
             if op.public and op.name not in ("add", "sub", "mul", "div", "neg", "pow")}

#: Named constants of the expression language.
CONSTANTS = {"pi": math.pi, "e": math.e}

#: exp of an argument below EXP_FLOOR over a segment (or at a point, with
#: its error) is taken as the constant [0, EXP_TINY] (EXP_TINY >= e^-80 =
#: 1.80e-35, a normal float32), in a branch that a packet skips where all
#: its lanes are below: a Gaussian or Blinn blob far from its centre costs
#: no exp, no chord and no error bound (per-region simplification, decided
#: on each segment from the argument's form).
NEGLIGIBLE_EXP = True
EXP_FLOOR = -80.0
EXP_TINY = 1.81e-35
