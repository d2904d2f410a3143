"""The expression DAG: hash-consed nodes built by operator overloading.

Pipeline: expression (this module, :mod:`.parser`) -> derivatives
(:mod:`.diff`) -> evaluators (:mod:`.evaluate`: values and intervals over
numpy or Dr.Jit arrays). A node is ``(op, args, param)``; ``op`` names a row of
the op table in :mod:`.ops`. Nodes are interned, so equal subexpressions are
one object and the DAG shares them; light algebraic simplification (constant
folding, ``x + 0``, ``x * 1``...) happens at construction.
"""
from __future__ import annotations

import math
import numbers

_interned: dict = {}


class Expr:
    """One node of an implicit function f(x, y, z). Build with ``x, y, z``
    and Python operators, or with :func:`lgshape.parse`."""

    __slots__ = ("op", "args", "param", "__weakref__")

    def __new__(cls, op: str, args: tuple = (), param=None):
        key = (op, tuple(id(a) for a in args), param)
        node = _interned.get(key)
        if node is None:
            node = object.__new__(cls)
            node.op, node.args, node.param = op, tuple(args), param
            _interned[key] = node
        return node

    # -- construction with simplification ---------------------------------
    @staticmethod
    def lift(v) -> "Expr":
        if isinstance(v, Expr):
            return v
        if isinstance(v, numbers.Real) and not isinstance(v, bool):
            v = float(v)
            if not math.isfinite(v):
                raise ValueError(f"constant {v} is not finite")
            return Expr("const", (), v + 0.0)  # + 0.0 folds -0.0 into 0.0
        raise TypeError(f"cannot use {type(v).__name__} {v!r} in an expression")

    @property
    def is_const(self) -> bool:
        return self.op == "const"

    def _is(self, value: float) -> bool:
        return self.op == "const" and self.param == value

    def __add__(self, o):
        return add(self, o)

    def __radd__(self, o):
        return add(o, self)

    def __sub__(self, o):
        return sub(self, o)

    def __rsub__(self, o):
        return sub(o, self)

    def __mul__(self, o):
        return mul(self, o)

    def __rmul__(self, o):
        return mul(o, self)

    def __truediv__(self, o):
        return div(self, o)

    def __rtruediv__(self, o):
        return div(o, self)

    def __neg__(self):
        return neg(self)

    def __pos__(self):
        return self

    def __abs__(self):
        return abs_(self)

    def __pow__(self, n):
        return power(self, n)

    def __repr__(self) -> str:
        from .printer import to_string
        return to_string(self)

    def __bool__(self):
        raise TypeError("an expression has no truth value")

    # -- traversal ---------------------------------------------------------
    def nodes(self) -> list["Expr"]:
        """All nodes of the DAG below and including ``self``, children first."""
        return topological([self])

    def size(self) -> int:
        return len(self.nodes())


def topological(roots) -> list[Expr]:
    order, seen, stack = [], set(), [(r, False) for r in reversed(roots)]
    while stack:
        node, expanded = stack.pop()
        if id(node) in seen:
            continue
        if expanded:
            seen.add(id(node))
            order.append(node)
        else:
            stack.append((node, True))
            stack.extend((a, False) for a in reversed(node.args) if id(a) not in seen)
    return order


def const(v: float) -> Expr:
    return Expr.lift(v)


def var(name: str) -> Expr:
    return Expr("var", (), name)


ZERO, ONE = const(0.0), const(1.0)


def _node(op, *args, param=None) -> Expr:
    """The node op(args), folded to a constant when every argument is one."""
    if all(a.is_const for a in args):
        from ..arraymath import NUMPY
        from .ops import OPS
        import numpy as np
        extra = (param,) if param is not None else ()
        with np.errstate(all="ignore"):
            v = float(OPS[op].value(NUMPY, *[np.float64(a.param) for a in args], *extra))
        if math.isfinite(v):
            return const(v)
    return Expr(op, args, param)


def add(a, b) -> Expr:
    a, b = Expr.lift(a), Expr.lift(b)
    if a._is(0.0):
        return b
    if b._is(0.0):
        return a
    if b.op == "neg":
        return sub(a, b.args[0])
    return _node("add", a, b)


def sub(a, b) -> Expr:
    a, b = Expr.lift(a), Expr.lift(b)
    if b._is(0.0):
        return a
    if a._is(0.0):
        return neg(b)
    if a is b:
        return ZERO
    if b.op == "neg":
        return add(a, b.args[0])
    return _node("sub", a, b)


def mul(a, b) -> Expr:
    a, b = Expr.lift(a), Expr.lift(b)
    if a._is(0.0) or b._is(0.0):
        return ZERO
    if a._is(1.0):
        return b
    if b._is(1.0):
        return a
    if a._is(-1.0):
        return neg(b)
    if b._is(-1.0):
        return neg(a)
    if b.is_const and not a.is_const:  # constants first: c * e
        a, b = b, a
    return _node("mul", a, b)


def div(a, b) -> Expr:
    a, b = Expr.lift(a), Expr.lift(b)
    if b._is(1.0):
        return a
    if a._is(0.0) and not b._is(0.0):
        return ZERO
    return _node("div", a, b)


def neg(a) -> Expr:
    a = Expr.lift(a)
    if a.op == "neg":
        return a.args[0]
    return _node("neg", a)


def power(a, n) -> Expr:
    """``a ** n`` for an integer n (negative n means ``1 / a ** -n``)."""
    a = Expr.lift(a)
    if isinstance(n, Expr):
        if not n.is_const:
            raise ValueError("the exponent of ^ must be a constant integer")
        n = n.param
    if isinstance(n, bool) or not isinstance(n, numbers.Real) or float(n) != int(n):
        raise ValueError(f"only integer powers are supported (got {n!r}); use sqrt() for roots")
    n = int(n)
    if n < 0:
        return div(ONE, power(a, -n))
    if n == 0:
        return ONE
    if n == 1:
        return a
    return _node("pow", a, param=n)


def unary(op: str):
    def make(a) -> Expr:
        a = Expr.lift(a)
        return _node(op, a)
    make.__name__ = op
    return make


sqrt, exp, log, sin, cos, abs_, step, kink = (
    unary(o) for o in ("sqrt", "exp", "log", "sin", "cos", "abs", "step", "kink"))


def minimum(a, b, *more) -> Expr:
    a, b = Expr.lift(a), Expr.lift(b)
    r = a if a is b else (_node("min", a, b))
    return minimum(r, *more) if more else r


def maximum(a, b, *more) -> Expr:
    a, b = Expr.lift(a), Expr.lift(b)
    r = a if a is b else (_node("max", a, b))
    return maximum(r, *more) if more else r
