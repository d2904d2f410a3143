"""Exact symbolic derivatives on the DAG (forward mode, never finite
differences).

``derivative(f, seeds)`` pushes the seeds (the derivative of each variable)
through every node with the op table's derivative rule. The gradient seeds
one axis at a time; the ray derivatives seed the direction variables
``dx, dy, dz``: g = d . grad f = dF/dt and h = d^T H d = d^2F/dt^2. Results
are interned expressions, so they share nodes with f and with each other.
"""
from __future__ import annotations

from functools import lru_cache

from .node import ZERO, Expr, const, topological, var
from .ops import OPS

DX, DY, DZ = var("dx"), var("dy"), var("dz")
X, Y, Z = var("x"), var("y"), var("z")


def derivative(f: Expr, seeds: dict[str, Expr]) -> Expr:
    d = {}
    for n in topological([f]):
        if n.op == "const":
            d[id(n)] = ZERO
        elif n.op == "var":
            d[id(n)] = Expr.lift(seeds.get(n.param, ZERO))
        else:
            d[id(n)] = OPS[n.op].deriv(n, n.args, [d[id(a)] for a in n.args])
    return d[id(f)]


@lru_cache(maxsize=256)
def gradient(f: Expr) -> tuple[Expr, Expr, Expr]:
    one = const(1.0)
    return tuple(derivative(f, {v: one}) for v in ("x", "y", "z"))


@lru_cache(maxsize=256)
def hessian(f: Expr) -> tuple[tuple[Expr, ...], ...]:
    g = gradient(f)
    return tuple(gradient(gi) for gi in g)


@lru_cache(maxsize=256)
def ray_derivatives(f: Expr) -> tuple[Expr, Expr]:
    """(g, h): first and second derivative of F(t) = f(o + t d), as
    expressions in x, y, z and the direction dx, dy, dz."""
    seeds = {"x": DX, "y": DY, "z": DZ}
    g = derivative(f, seeds)
    h = derivative(g, seeds)
    return g, h
