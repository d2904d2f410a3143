"""Box-local coordinates: f(c + u) as an expression in u.

Far from the origin, float32 cannot resolve small features (at 1e4 its step
is 1e-3), and float64 loses digits in ``x - 10000``. The search therefore
evaluates f in coordinates local to its box: :func:`localize` substitutes
``x -> x + c_x`` (and y, z) and folds the constants that meet, so the sphere
``(x - 10000)^2 + ...`` becomes ``x^2 + ...`` about a centre c = (10000, ...).

Folding is exact or not done: ``(u + c) + k`` becomes ``u + (c + k)`` only
when c + k is exactly representable (checked with rationals), so the local
expression is the same function as f, not a rounded neighbour of it.
"""
from __future__ import annotations

from fractions import Fraction

from . import node as N
from .node import Expr, topological

_REBUILD = {"add": N.add, "sub": N.sub, "mul": N.mul, "div": N.div, "neg": N.neg}


def _offset(e: Expr):
    """(base, c) where e is base + c with a constant c, else (e, 0)."""
    if e.op == "add" and e.args[1].is_const:
        return e.args[0], e.args[1].param
    if e.op == "add" and e.args[0].is_const:
        return e.args[1], e.args[0].param
    if e.op == "sub" and e.args[1].is_const:
        return e.args[0], -e.args[1].param
    return e, 0.0


def _exact_sum(a: float, b: float):
    s = a + b
    return s if Fraction(a) + Fraction(b) == Fraction(s) else None


def _plus(base: Expr, c: float) -> Expr:
    return N.add(base, c) if c >= 0 else N.sub(base, -c)


def _add(a: Expr, b: Expr, sign: float) -> Expr:
    """a + sign * b, merging constant offsets exactly."""
    (ba, ca), (bb, cb) = _offset(a), _offset(b)
    if a.is_const:
        ba, ca = None, a.param
    if b.is_const:
        bb, cb = None, b.param
    s = _exact_sum(ca, sign * cb) if (ca != 0.0 and cb != 0.0) else None
    if s is not None:
        if ba is None and bb is None:
            return N.const(s)
        if bb is None:
            return _plus(ba, s)
        if ba is None:
            return _plus(bb if sign > 0 else N.neg(bb), s)
        return _plus(N.add(ba, bb) if sign > 0 else N.sub(ba, bb), s)
    return N.add(a, b) if sign > 0 else N.sub(a, b)


def localize(f: Expr, centre, named_centre: bool = False) -> Expr:
    """f(centre + u) as an expression in u (named x, y, z). With
    ``named_centre``, the centre enters as named constants (never folded):
    the expression's structure is then the same for any centre, at the cost
    of the exact folding that keeps far-away geometry precise."""
    out = {}
    for n in topological([f]):
        if n.op == "var" and n.param in ("x", "y", "z"):
            c = float(centre["xyz".index(n.param)])
            if named_centre:
                r = N.add(n, N.named("centre_" + n.param, c))
            else:
                r = n if c == 0.0 else _plus(n, c)
        elif n.op in ("const", "named", "var"):
            r = n
        else:
            args = [out[id(a)] for a in n.args]
            if n.op == "add":
                r = _add(args[0], args[1], 1.0)
            elif n.op == "sub":
                r = _add(args[0], args[1], -1.0)
            elif n.op in _REBUILD:
                r = _REBUILD[n.op](*args)
            elif n.op == "pow":
                r = N.power(args[0], n.param)
            else:
                r = N._node(n.op, *args, param=n.param)
        out[id(n)] = r
    return out[id(f)]
