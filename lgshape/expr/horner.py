"""Sums of powers of one subexpression rewritten in Horner form.

A sum such as 1 - 4/9 u^3 + 17/9 u^2 - 22/9 u (Wyvill's soft-object kernel
of u = r^2 / R^2) evaluates u^3 and u^2 as separate products; as
1 + u (-22/9 + u (17/9 - 4/9 u)) it takes two. On the search's expression
path every evaluation (point values with error bounds, quadratic forms along
the ray, g's derivative expression) costs per node, so the rewrite makes
each cheaper. The function is the same; the rounding differs, and the
evaluators bound the rounding of whatever they evaluate.

Only terms c u^k (c a plain constant, k >= 1) of one sum (add, sub, neg)
that share the same u, with at least two powers, one of them >= 2, and at
most one power missing below the highest, are regrouped; everything else
is kept as it is.
"""
from __future__ import annotations

from . import node as N
from .node import Expr, topological


def horner(f: Expr) -> Expr:
    """f with each sum's powers of a common subexpression in Horner form.

    Each sum is regrouped once, at its outermost node (one used by a node
    other than a sum, or f itself); a sum node used by sums only is rebuilt
    on its rewritten arguments (its terms are regrouped with the whole
    sum's), so the time is linear in the size of f, not quadratic in a
    sum's length."""
    nodes = topological([f])
    outer = {id(f)}          # nodes used by a node that is not add or sub
    for n in nodes:
        if n.op != "add" and n.op != "sub":
            outer.update(id(a) for a in n.args)
    out: dict[int, Expr] = {}
    for n in nodes:
        if not n.args:
            out[id(n)] = n
        elif n.op in ("add", "sub") and id(n) in outer:
            out[id(n)] = _sum(n, out)
        elif n.op == "pow":
            out[id(n)] = N.power(out[id(n.args[0])], n.param)
        else:
            out[id(n)] = N._node(n.op, *[out[id(a)] for a in n.args], param=n.param)
    return out[id(f)]


def _terms(n: Expr, sign: float, acc: list):
    """The terms of the sum tree at n, with their signs (original nodes),
    left to right. Iterative: any depth."""
    stack = [(n, sign)]
    while stack:
        n, sign = stack.pop()
        if n.op == "add":
            stack.append((n.args[1], sign))
            stack.append((n.args[0], sign))
        elif n.op == "sub":
            stack.append((n.args[1], -sign))
            stack.append((n.args[0], sign))
        elif n.op == "neg":
            stack.append((n.args[0], -sign))
        else:
            acc.append((sign, n))


def _power_of(e: Expr):
    """(coefficient, base, k) of a term c * u^k (c plain, k >= 1), or None."""
    c = 1.0
    if e.op == "mul" and e.args[0].op == "const":
        c, e = e.args[0].param, e.args[1]
    if e.op == "const" or e.op == "named":
        return None
    if e.op == "pow" and e.param >= 1:
        return c, e.args[0], e.param
    return c, e, 1


def _sum(n: Expr, out: dict) -> Expr:
    terms: list = []
    _terms(n, 1.0, terms)
    # group the powers by their base (the rewritten one)
    groups: dict[int, tuple[Expr, dict[int, float]]] = {}
    rest = []
    for sign, t in terms:
        p = _power_of(out[id(t)])
        if p is None:
            rest.append((sign, out[id(t)]))
            continue
        c, u, k = p
        base, coefs = groups.setdefault(id(u), (u, {}))
        coefs[k] = coefs.get(k, 0.0) + sign * c
    if not any(_dense(coefs) for _, coefs in groups.values()):
        # nothing to regroup: n with its rewritten arguments
        return N._node(n.op, *[out[id(a)] for a in n.args])
    total = None
    for sign, t in rest:
        total = _plus(total, t, sign)
    for u, coefs in groups.values():
        if _dense(coefs):
            # sum_k c_k u^k = u (c_1 + u (c_2 + ... + u c_K))
            h = None
            for k in range(max(coefs), 0, -1):
                h = N.const(coefs.get(k, 0.0)) if h is None else N.add(coefs.get(k, 0.0),
                                                                       N.mul(u, h))
            total = _plus(total, N.mul(u, h), 1.0)
        else:
            for k, c in coefs.items():
                total = _plus(total, N.mul(c, N.power(u, k)), 1.0)
    return total


def _dense(coefs: dict) -> bool:
    """Powers worth regrouping: at least two, one >= 2, and at most one of
    the powers up to the highest missing (x^4 - 5 x^2 is cheaper as it is
    than as x (x (x x - 5)))."""
    return len(coefs) >= 2 and max(coefs) >= 2 and len(coefs) >= max(coefs) - 1


def _plus(total, t: Expr, sign: float) -> Expr:
    if total is None:
        return t if sign > 0 else N.neg(t)
    return N.add(total, t) if sign > 0 else N.sub(total, t)
