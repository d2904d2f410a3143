"""Expressions back to text in the expression language (round-trips
through :func:`lgshape.parse`).

The text is written by one iterative walk with an explicit stack (so any
depth prints), appending pieces to a list that is joined once: the time is
linear in the length of the text. The text spells the DAG out as a tree; a
subexpression used more than once is written once, kept as a string and
copied where it recurs, so shared parts cost a string copy, not another walk.
"""
from __future__ import annotations

from .node import topological

_PREC = {"add": 1, "sub": 1, "mul": 2, "div": 2, "neg": 3, "pow": 4}
_SYM = {"add": " + ", "sub": " - ", "mul": "*", "div": "/"}
_ATOM = 5   # precedence of constants, variables and calls: never parenthesised


def _leaf(n) -> str:
    if n.op in ("const", "named"):          # a named constant prints its value
        v = n.param if n.op == "const" else n.param[1]
        s = repr(int(v)) if v == int(v) and abs(v) < 1e15 else repr(v)
        return s if v >= 0 else f"({s})"
    return n.param  # a variable


def to_string(e) -> str:
    uses: dict = {}
    for n in topological([e]):
        for a in n.args:
            uses[id(a)] = uses.get(id(a), 0) + 1
    shared: dict = {}     # id -> text, for nodes used more than once
    out: list = []
    # Work items: a str is appended as is; (node, need) writes the node,
    # parenthesised when its precedence is below `need`; (None, node, start)
    # closes a shared node: out[start:] becomes its memoised text.
    stack: list = [(e, 0)]
    while stack:
        item = stack.pop()
        if isinstance(item, str):
            out.append(item)
            continue
        if item[0] is None:
            _, n, start = item
            text = "".join(out[start:])
            del out[start:]
            out.append(text)
            shared[id(n)] = text
            continue
        n, need = item
        op = n.op
        p = _PREC.get(op, _ATOM)
        if p < need:
            out.append("(")
            stack.append(")")
        text = shared.get(id(n))
        if text is not None:
            out.append(text)
            continue
        if not n.args:
            out.append(_leaf(n))
            continue
        if uses.get(id(n), 0) > 1:
            stack.append((None, n, len(out)))
        # Push the pieces of n in reverse order.
        args = n.args
        if op == "neg":
            stack.append((args[0], 4))
            out.append("-")
        elif op == "pow":
            stack.append(f"^{n.param}")
            stack.append((args[0], _ATOM))
        elif op in _SYM:
            stack.append((args[1], p + 1))
            stack.append(_SYM[op])
            stack.append((args[0], p))
        else:   # a function call
            stack.append(")")
            for i in range(len(args) - 1, 0, -1):
                stack.append((args[i], 0))
                stack.append(", ")
            stack.append((args[0], 0))
            out.append(f"{op}(")
    return "".join(out)
