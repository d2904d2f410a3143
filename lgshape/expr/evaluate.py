"""Evaluators: values and intervals of expressions over numpy or Dr.Jit arrays.

Both walk the DAG once, children first, memoising every node, so a shared
subexpression is computed once and several roots (f, g, dT H d...) share their
work. Variables come from ``env`` (name -> array or Interval). In Dr.Jit the
walk happens while tracing, so the result is one fused kernel.
"""
from __future__ import annotations

from .. import interval as iv
from ..arraymath import math_for, zero_like
from ..pointerror import SAFETY
from .node import Expr, topological
from . import ops
from .ops import OPS


def constant(n, m):
    """The array value of a ``const`` or ``named`` leaf (opaque in Dr.Jit,
    see :meth:`~lgshape.arraymath.DrJitMath.const`)."""
    return m.const(n.param) if n.op == "const" else m.named(*n.param)


def _lookup(env, name):
    try:
        return env[name]
    except KeyError:
        raise KeyError(f"no value given for variable {name!r}") from None


def evaluate(roots, env: dict, m=None):
    """Point values of ``roots`` (an Expr or a list of them)."""
    single = isinstance(roots, Expr)
    roots = [roots] if single else list(roots)
    if m is None:
        m = math_for(next(iter(env.values())))
    memo = {}
    with m.errstate():
        for n in topological(roots):
            if n.op in ("const", "named"):
                v = constant(n, m)
            elif n.op == "var":
                v = _lookup(env, n.param)
            else:
                op = OPS[n.op]
                args = [memo[id(a)] for a in n.args]
                v = op.value(m, *args, n.param) if n.op == "pow" else op.value(m, *args)
            memo[id(n)] = v
    out = [memo[id(r)] for r in roots]
    return out[0] if single else out


def evaluate_interval(roots, env: dict, m):
    """Interval bounds of ``roots`` over the intervals given in ``env``.

    ``env`` values may be :class:`~lgshape.interval.Interval` or plain arrays
    (exact points, such as the ray direction); a node whose arguments are all
    plain stays plain, so constants and directions cost no interval work.
    Returned values are Intervals (plain results are promoted)."""
    single = isinstance(roots, Expr)
    roots = [roots] if single else list(roots)
    memo = {}
    maybe_empty = set()      # nodes below a sqrt or log: empty where undefined
    with m.errstate():
        for n in topological(roots):
            if n.op in ("const", "named"):
                memo[id(n)] = constant(n, m)
                continue
            if n.op == "var":
                memo[id(n)] = _lookup(env, n.param)
                continue
            op = OPS[n.op]
            args = [memo[id(a)] for a in n.args]
            extra = (n.param,) if n.op == "pow" else ()
            if not any(isinstance(a, iv.Interval) for a in args):
                memo[id(n)] = op.value(m, *args, *extra)
                continue
            if n.op == "mul" and not isinstance(args[0], iv.Interval):
                r = iv.i_scale(m, args[0], args[1])
            elif n.op == "mul" and not isinstance(args[1], iv.Interval):
                r = iv.i_scale(m, args[1], args[0])
            else:
                r = op.interval(m, *[iv.promote(m, a) for a in args], *extra)
            # Exact rules (neg, abs, min, max...) select among their inputs'
            # bounds: nothing to round, no NaN to create. An integer power
            # rounds up to n times along its chain of products.
            if not op.exact:
                r = iv.pad(m, r, op.rounding, scale=float(n.param) if n.op == "pow" else 1.0)
            if op.nonneg or (n.op == "pow" and n.param % 2 == 0):
                r = iv.nonneg(m, r)
            # Undefined where an argument is: empty propagates.
            below = [a for a in n.args if id(a) in maybe_empty]
            if below:
                e = iv.is_empty(m, memo[id(below[0])])
                for a in below[1:]:
                    e = e | iv.is_empty(m, memo[id(a)])
                r = iv.emptied(m, r, e)
            if below or n.op in ("sqrt", "log"):
                maybe_empty.add(id(n))
            memo[id(n)] = r
    out = [iv.promote(m, memo[id(r)]) for r in roots]
    return out[0] if single else out


def _exp_with_error(m, op, a, ea):
    """exp(a) and its error bound, where some lane's a + ea reaches EXP_FLOOR
    - 1 (the margin covers the rounding of a + ea); [0, EXP_TINY] elsewhere."""
    zero = zero_like(a)
    low = a + ea < ops.EXP_FLOOR - 1.0

    def full():
        v = op.value(m, a)
        return v, op.error(m, v, a, ea)
    return m.branch(~low, full, lambda: (zero, zero + ops.EXP_TINY), label="lgshape_exp_point")


def evaluate_with_error(roots, env: dict, env_error: dict, m, safety: bool = True):
    """Point values of ``roots`` with bounds on their rounding error.

    ``env`` gives the computed variable values, ``env_error`` bounds on
    their errors (absolute; a missing name is exact). Returns a list of
    ``(value, error)`` pairs: |exact root at the exact inputs - value| <=
    error, by the op table's point-error rules (:mod:`lgshape.pointerror`).
    ``m`` must provide ``u`` (unit roundoff) and ``eps_t``. The bounds are
    multiplied by :data:`~lgshape.pointerror.SAFETY` once, at the end;
    ``safety=False`` leaves that to the caller (for parts of a larger
    evaluation, such as the rows of a table, so it is applied once)."""
    single = isinstance(roots, Expr)
    roots = [roots] if single else list(roots)
    val, err = {}, {}
    with m.errstate():
        for n in topological(roots):
            if n.op in ("const", "named"):
                val[id(n)] = constant(n, m)
                err[id(n)] = 0.0
                continue
            if n.op == "var":
                val[id(n)] = _lookup(env, n.param)
                err[id(n)] = env_error.get(n.param, 0.0)
                continue
            op = OPS[n.op]
            args = [val[id(a)] for a in n.args]
            errs = [err[id(a)] for a in n.args]
            if n.op == "exp" and ops.NEGLIGIBLE_EXP:
                val[id(n)], err[id(n)] = _exp_with_error(m, op, args[0], errs[0])
                continue
            extra = (n.param,) if n.op == "pow" else ()
            v = op.value(m, *args, *extra)
            val[id(n)] = v
            err[id(n)] = op.error(m, v, *args, *errs, *extra)
    k = SAFETY if safety else 1.0
    out = [(val[id(r)], err[id(r)] * k) for r in roots]
    return out[0] if single else out
