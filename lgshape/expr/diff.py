"""Exact symbolic derivatives on the DAG (forward mode, never finite
differences).

``derivative(f, seeds)`` pushes the seeds (the derivative of each variable)
through every node with the op table's derivative rule. The gradient seeds
one axis at a time; the ray derivatives seed the direction variables
``dx, dy, dz``: g = d . grad f = dF/dt and h = d^T H d = d^2F/dt^2. Results
are interned expressions, so they share nodes with f and with each other.

Every pass is one iterative walk over the DAG (:func:`.node.topological`),
so any depth works and the time is linear in the number of nodes; the
gradient pushes its three seeds in the same walk, and the Hessian
differentiates the three gradient components in one walk too (they share
most of their nodes).
"""
from __future__ import annotations

from functools import lru_cache

from .node import ZERO, Expr, add, const, mul, neg, product_chain, sub, topological, var
from .ops import OPS

DX, DY, DZ = var("dx"), var("dy"), var("dz")
X, Y, Z = var("x"), var("y"), var("z")


# Ops whose derivative rule gives the constant 0 whenever every argument's
# derivative is 0, so that the rule need not run (nor build nodes that fold
# away): every op but step (its rule is kink(c) whatever the seeds), div and
# log (a constant zero denominator leaves a 0/0 node). Leaving an op out only
# costs time.
_ZERO_IN_ZERO_OUT = frozenset({"add", "sub", "mul", "neg", "pow", "sqrt", "exp", "sin", "cos",
                               "abs", "min", "max", "kink"})


def _derivatives(roots, seedings) -> list[tuple[Expr, ...]]:
    """For each root, its derivatives under each of the seedings (dicts
    variable name -> derivative of that variable), in one walk."""
    k = len(seedings)
    zeros = (ZERO,) * k
    d = {}
    for n in topological(roots):
        op = n.op
        if op in ("const", "named"):
            d[id(n)] = zeros
        elif op == "var":
            d[id(n)] = tuple(Expr.lift(s.get(n.param, ZERO)) for s in seedings)
        else:
            rule, args = OPS[op].deriv, n.args
            da = [d[id(a)] for a in args]
            if op in _ZERO_IN_ZERO_OUT:
                d[id(n)] = tuple(ZERO if all(t[j] is ZERO for t in da)
                                 else _factored(rule(n, args, [t[j] for t in da]))
                                 for j in range(k))
            else:
                d[id(n)] = tuple(_factored(rule(n, args, [t[j] for t in da])) for j in range(k))
    return [d[id(r)] for r in roots]


#: How many nodes of a product chain :func:`_product` looks through.
_FACTOR_SCAN = 32


def _product(e: Expr):
    """e's chain of products and negations (:func:`.node.product_chain`),
    its plain constants apart; None past ``_FACTOR_SCAN`` nodes."""
    return product_chain(e, lambda n: n.op == "const", _FACTOR_SCAN)


def _rebuilt(negated, consts, factors) -> Expr:
    """The product again; constants are multiplied as nodes, never folded
    into one rounded number (the derivative stays the exact one)."""
    out = None
    for f in factors:
        out = f if out is None else mul(out, f)
    for c in consts:
        out = c if out is None else (Expr("mul", (c, out)) if out.op == "const"
                                     else mul(c, out))
    out = const(1.0) if out is None else out
    return neg(out) if negated else out


def _factored(e: Expr) -> Expr:
    """A sum or difference of two products with common factors, as the
    product of those factors and the sum of the rest: a P(m) dm + b Q(m) dm
    -> (a P(m) + b Q(m)) dm. The chain rule distributes an argument's
    derivative over every term of a polynomial in it; kept factored, an
    enclosure sees that the terms' partials cancel (a blob's kernel has
    zero slope where it is clamped: bounded term by term, the step of the
    clamp's derivative multiplies each term's range, not their sum's).
    Interval arithmetic is subdistributive, so the factored form's
    enclosures are never wider; the value is the same real number."""
    if e.op not in ("add", "sub"):
        return e
    pa, pb = _product(e.args[0]), _product(e.args[1])
    if pa is None or pb is None:
        return e
    rest_b = list(pb[2])
    common, rest_a = [], []
    for f in pa[2]:
        for i, g in enumerate(rest_b):
            if g is f:
                common.append(f)
                del rest_b[i]
                break
        else:
            rest_a.append(f)
    if not common:
        return e
    a, b = _rebuilt(pa[0], pa[1], rest_a), _rebuilt(pb[0], pb[1], rest_b)
    out = add(a, b) if e.op == "add" else sub(a, b)
    for f in common:
        out = mul(out, f)
    return out


def derivative(f: Expr, seeds: dict[str, Expr]) -> Expr:
    """The derivative of f when each variable v has derivative seeds[v]
    (0 for a variable not named)."""
    return _derivatives([f], [seeds])[0][0]


_AXES = tuple({v: const(1.0)} for v in ("x", "y", "z"))


@lru_cache(maxsize=256)
def gradient(f: Expr) -> tuple[Expr, Expr, Expr]:
    return _derivatives([f], _AXES)[0]


@lru_cache(maxsize=256)
def hessian(f: Expr) -> tuple[tuple[Expr, ...], ...]:
    return tuple(_derivatives(list(gradient(f)), _AXES))


@lru_cache(maxsize=256)
def ray_derivatives(f: Expr) -> tuple[Expr, Expr]:
    """(g, h): first and second derivative of F(t) = f(o + t d), as
    expressions in x, y, z and the direction dx, dy, dz."""
    seeds = {"x": DX, "y": DY, "z": DZ}
    g = derivative(f, seeds)
    h = derivative(g, seeds)
    return g, h
