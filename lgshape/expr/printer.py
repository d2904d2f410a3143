"""Expressions back to text in the expression language (round-trips
through :func:`lgshape.parse`)."""
from __future__ import annotations

from .node import topological

_PREC = {"add": 1, "sub": 1, "mul": 2, "div": 2, "neg": 3, "pow": 4}


def to_string(e) -> str:
    text = {}
    for n in topological([e]):
        text[id(n)] = _format(n, text)
    return text[id(e)][0]


def _format(n, text):
    """(string, precedence) of node n."""
    if n.op == "const":
        v = n.param
        s = repr(int(v)) if v == int(v) and abs(v) < 1e15 else repr(v)
        return (s, 5) if v >= 0 else (f"({s})", 5)
    if n.op == "var":
        return n.param, 5
    args = [text[id(a)] for a in n.args]
    p = _PREC.get(n.op)
    if p is None:
        return f"{n.op}({', '.join(a[0] for a in args)})", 5

    def wrap(a, need):
        return a[0] if a[1] >= need else f"({a[0]})"

    if n.op == "neg":
        return "-" + wrap(args[0], 4), 3
    if n.op == "pow":
        return f"{wrap(args[0], 5)}^{n.param}", 4
    sym = {"add": " + ", "sub": " - ", "mul": "*", "div": "/"}[n.op]
    return wrap(args[0], p) + sym + wrap(args[1], p + 1), p
