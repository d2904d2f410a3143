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
        key = (op, param, *map(id, args))
        node = _interned.get(key)
        if node is None:
            node = object.__new__(cls)
            node.op, node.args, node.param = op, tuple(args), param
            _interned[key] = node
        return node

    # -- construction with simplification ---------------------------------
    @staticmethod
    def lift(v) -> "Expr":
        if v.__class__ is Expr or isinstance(v, Expr):
            return v
        t = type(v)
        if t is float or t is int or (isinstance(v, numbers.Real) and t is not bool):
            try:
                f = float(v)
            except OverflowError:   # an int beyond the float64 range
                f = math.inf
            if not math.isfinite(f):
                shown = repr(v) if len(repr(v)) <= 24 else f"{repr(v)[:12]}...{repr(v)[-8:]}"
                raise ValueError(f"constant {shown} is not finite: an expression's constants "
                                 f"are finite float64 values")
            return Expr("const", (), f + 0.0)  # + 0.0 folds -0.0 into 0.0
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
        from .printer import to_string      # (late: printer imports this module)
        return to_string(self)

    def __bool__(self):
        raise TypeError("an expression has no truth value")

    # -- traversal ---------------------------------------------------------
    def nodes(self) -> list["Expr"]:
        """All nodes of the DAG below and including ``self``, children first."""
        return topological([self])

    def size(self) -> int:
        return len(self.nodes())

    def degree(self) -> float:
        """The degree of f as a polynomial in x, y, z (inf where it is not
        one: sqrt, sin, min, division by a non-constant, ...). Structural:
        x * x - x * x has degree 2."""
        deg = {}
        for n in self.nodes():
            a = [deg[id(c)] for c in n.args]
            if n.op == "var":
                d = 1 if n.param in ("x", "y", "z") else 0
            elif not a:
                d = 0
            elif n.op in ("add", "sub"):
                d = max(a)
            elif n.op == "mul":
                d = a[0] + a[1]
            elif n.op == "neg":
                d = a[0]
            elif n.op == "pow":
                d = a[0] * n.param if n.param >= 0 else (0 if a[0] == 0 else math.inf)
            elif n.op == "div":
                d = a[0] if a[1] == 0 else math.inf
            else:
                d = 0 if max(a) == 0 else math.inf
            deg[id(n)] = d
        return deg[id(self)]


def topological(roots) -> list[Expr]:
    """Every node below ``roots``, each once, children before parents (the
    post-order of a depth-first walk taking arguments left to right).
    Iterative, with an explicit stack: any depth, linear time."""
    order, seen = [], set()
    append, mark = order.append, seen.add
    for root in roots:
        if id(root) in seen:
            continue
        mark(id(root))
        stack = [root]
        push, pop = stack.append, stack.pop
        while stack:
            for a in stack[-1].args:  # at most two: rescanning them is cheap
                if id(a) not in seen:
                    mark(id(a))
                    push(a)
                    break
            else:
                append(pop())
    return order


def product_chain(e: Expr, is_constant, limit: int | None = None):
    """e as +-(c1 * c2 * ...) * (f1 * f2 * ...) through its products and
    negations: (negated, [c1, ...], [f1, ...]), the c the nodes where
    ``is_constant`` holds; None past ``limit`` nodes."""
    negated, consts, factors, stack = False, [], [], [e]
    seen = 0
    while stack:
        seen += 1
        if limit is not None and seen > limit:
            return None
        n = stack.pop()
        if n.op == "mul":
            stack.extend(n.args)
        elif n.op == "neg":
            negated = not negated
            stack.append(n.args[0])
        elif is_constant(n):
            consts.append(n)
        else:
            factors.append(n)
    return negated, consts, factors


def const(v: float) -> Expr:
    return Expr.lift(v)


def var(name: str) -> Expr:
    return Expr("var", (), name)


def named(name: str, value: float) -> Expr:
    """A named constant (a scene parameter): a leaf with the value ``value``
    that construction never folds or merges with another constant of the
    same value, so the expression's structure, and with it the compiled
    kernel, does not depend on the value (0, 1 or a value that another
    constant happens to have included)."""
    c = Expr.lift(value)                     # checks: a finite number
    return Expr("named", (), (str(name), c.param))


ZERO, ONE = const(0.0), const(1.0)


_fold = None  # (NUMPY, OPS, numpy), imported on first use (ops imports this module)
_ARITH = {"add": lambda a, b: a + b, "sub": lambda a, b: a - b, "mul": lambda a, b: a * b,
          "div": lambda a, b: a / b, "neg": lambda a, b: -a}


def _node(op, *args, param=None) -> Expr:
    """The node op(args), folded to a constant when every argument is one."""
    global _fold
    for a in args:
        if a.op != "const":
            return Expr(op, args, param)
    if op in _ARITH:   # correctly rounded in Python floats as in float64 numpy
        a = args[0].param
        b = args[1].param if len(args) == 2 else None
        if op == "div" and b == 0.0:
            return Expr(op, args, param)   # inf or nan: not folded
        v = _ARITH[op](a, b)
        return const(v) if math.isfinite(v) else Expr(op, args, param)
    if _fold is None:
        import numpy as np
        # (late: ops imports this module; numpy only where constants fold)
        from ..arraymath import NUMPY
        from .ops import OPS
        _fold = NUMPY, OPS, np
    NUMPY, OPS, np = _fold
    extra = (param,) if param is not None else ()
    with np.errstate(all="ignore"):
        v = float(OPS[op].value(NUMPY, *[np.float64(a.param) for a in args], *extra))
    if math.isfinite(v):
        return const(v)
    return Expr(op, args, param)


# The simplifying constructors below test constants inline (``x.op ==
# "const" and x.param == v``) rather than through methods: they run for every
# node that parsing and differentiation build.

def _term(e: Expr):
    """e as c * t, c a constant: (c, t); (1, e) for any other e."""
    if e.op == "mul" and e.args[0].op == "const":
        return e.args[0].param, e.args[1]
    return 1.0, e


def _like_terms(a: Expr, b: Expr, sign: float):
    """a + sign * b as one term (c_a + sign c_b) * t where a and b are
    constant multiples of one non-constant t (``x + x`` is ``2 * x``, ``3 *
    x + x`` is ``4 * x``), where c_a + sign c_b is exact in float64 (then
    the expression's real value is unchanged); None otherwise. This keeps a
    sum of n equal terms, as written out (``x + x + ... + x``), one node
    instead of n."""
    if a.op == "const" or b.op == "const":
        return None
    ca, ta = _term(a)
    cb, tb = _term(b)
    if ta is not tb:
        return None
    cb = sign * cb
    c = ca + cb
    if not math.isfinite(c):
        return None
    bv = c - ca                        # Knuth's TwoSum: the rounding error of c
    if (ca - (c - bv)) + (cb - bv) != 0.0:
        return None
    return mul(c, ta)


def add(a, b) -> Expr:
    if a.__class__ is not Expr:
        a = Expr.lift(a)
    if b.__class__ is not Expr:
        b = Expr.lift(b)
    if a.op == "const" and a.param == 0.0:
        return b
    if b.op == "const" and b.param == 0.0:
        return a
    if b.op == "neg":
        return sub(a, b.args[0])
    like = _like_terms(a, b, 1.0)
    if like is not None:
        return like
    return _node("add", a, b)


def sub(a, b) -> Expr:
    if a.__class__ is not Expr:
        a = Expr.lift(a)
    if b.__class__ is not Expr:
        b = Expr.lift(b)
    if b.op == "const" and b.param == 0.0:
        return a
    if a.op == "const" and a.param == 0.0:
        return neg(b)
    if a is b:
        return ZERO
    if b.op == "neg":
        return add(a, b.args[0])
    like = _like_terms(a, b, -1.0)
    if like is not None:
        return like
    return _node("sub", a, b)


def mul(a, b) -> Expr:
    if a.__class__ is not Expr:
        a = Expr.lift(a)
    if b.__class__ is not Expr:
        b = Expr.lift(b)
    a_const, b_const = a.op == "const", b.op == "const"
    if a_const or b_const:
        av = a.param if a_const else None
        bv = b.param if b_const else None
        if av == 0.0 or bv == 0.0:
            return ZERO
        if av == 1.0:
            return b
        if bv == 1.0:
            return a
        if av == -1.0:
            return neg(b)
        if bv == -1.0:
            return neg(a)
        if b_const and not a_const:  # constants first: c * e
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
        if n.op == "named":        # an exponent is structure: its value is used
            n = n.param[1]
        elif not n.is_const:
            raise ValueError("the exponent of ^ must be a constant integer")
        else:
            n = n.param
    if isinstance(n, bool) or not isinstance(n, numbers.Real) or (
            not isinstance(n, numbers.Integral) and not float(n).is_integer()):
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


def _reduce_balanced(op: str, args) -> Expr:
    """op(a0, a1, ..., an) for an associative, commutative, idempotent op
    (min, max), built as a balanced binary tree: adjacent pairs are combined
    level by level, so n arguments give n - 1 nodes of depth ceil(log2 n)
    instead of a chain n - 1 deep (which would make every later walk, and
    the kernel, as deep). Up to three arguments this is the left fold
    op(op(a0, a1), a2). Iterative: any number of arguments."""
    level = [Expr.lift(a) for a in args]
    while len(level) > 1:
        nxt = []
        for i in range(0, len(level) - 1, 2):
            a, b = level[i], level[i + 1]
            nxt.append(a if a is b else _node(op, a, b))
        if len(level) % 2:
            nxt.append(level[-1])
        level = nxt
    return level[0]


def minimum(a, b, *more) -> Expr:
    """min(a, b, ...) as a balanced tree of binary min nodes."""
    return _reduce_balanced("min", (a, b, *more))


def maximum(a, b, *more) -> Expr:
    """max(a, b, ...) as a balanced tree of binary max nodes."""
    return _reduce_balanced("max", (a, b, *more))


def _rebuilt(n: Expr, args) -> Expr:
    """n's op on new arguments, through the simplifying constructors."""
    op = n.op
    if op in ("add", "sub", "mul", "div"):
        return {"add": add, "sub": sub, "mul": mul, "div": div}[op](*args)
    if op == "neg":
        return neg(args[0])
    if op == "pow":
        return power(args[0], n.param)
    if op in ("min", "max"):
        a, b = args
        return a if a is b else _node(op, a, b)
    return _node(op, *args, param=n.param)


def constant_value(f: Expr):
    """The value of f where it does not depend on x, y, z once its named
    constants take their values (``1``, ``sqrt(2)``, ``a*x + 1`` with a =
    0): a float (NaN or infinite where f is undefined or overflows); None
    where f keeps a variable. Decided on the structure (each named constant
    replaced by its value and the DAG rebuilt through the simplifying
    constructors, linear in its size), never by sampling: ``x - x`` is 0,
    ``(x + 1)^2 - x^2 - 2*x - 1`` is not recognised."""
    nodes = topological([f])
    if any(n.op == "named" for n in nodes):
        out = {}
        for n in nodes:
            if n.op == "named":
                out[id(n)] = const(n.param[1])
            elif not n.args:
                out[id(n)] = n
            else:
                args = [out[id(a)] for a in n.args]
                out[id(n)] = n if all(a is b for a, b in zip(args, n.args)) else _rebuilt(n, args)
        f = out[id(f)]
        nodes = topological([f])
    if any(n.op == "var" for n in nodes):
        return None
    if f.op == "const":
        return f.param
    from ..arraymath import NUMPY       # (late, as in _node: numpy only where needed)
    from .evaluate import evaluate
    import numpy as np
    with np.errstate(all="ignore"):
        return float(evaluate(f, {}, NUMPY))
