"""Parser for the expression language (the same language the Python
operators build).

Grammar (whitespace is ignored; ``^`` and ``**`` are the same)::

    expr    := product (('+' | '-') product)*
    product := unary (('*' | '/') unary)*
    unary   := ('-' | '+') unary | power
    power   := atom (('^' | '**') unary)?        exponent: a constant integer
    atom    := NUMBER | NAME | NAME '(' expr (',' expr)* ')' | '(' expr ')'
    NAME    := x | y | z | pi | e | a function name
    NUMBER  := 12 | 1.5 | .5 | 1e-3 | 2.5E+2

Functions: sqrt, exp, log, sin, cos, abs (one argument), min, max (two or
more). ``-x^2`` is ``-(x^2)``; ``x^2^3`` is ``x^(2^3)``. Errors are
:class:`ParseError`, which names the position and what was expected.
"""
from __future__ import annotations

import re

from . import node as N
from .ops import CONSTANTS, FUNCTIONS

_TOKEN = re.compile(r"(?:(?P<num>(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)|(?P<name>[A-Za-z_]\w*)"
                    r"|(?P<op>\*\*|[-+*/^(),]))")

_BUILD = {"sqrt": N.sqrt, "exp": N.exp, "log": N.log, "sin": N.sin, "cos": N.cos,
          "abs": N.abs_, "min": N.minimum, "max": N.maximum}
assert set(_BUILD) == set(FUNCTIONS), "parser and op table disagree"


class ParseError(ValueError):
    """A malformed expression; ``pos`` is the 0-based character position."""

    def __init__(self, text: str, pos: int, message: str):
        self.text, self.pos = text, pos
        super().__init__(f"{message} at position {pos + 1}:\n  {text}\n  {' ' * pos}^")


class _Parser:
    def __init__(self, text: str):
        self.text = text
        self.tokens = []  # (kind, value, position)
        pos = 0
        while True:
            while pos < len(text) and text[pos].isspace():
                pos += 1
            if pos >= len(text):
                break
            m = _TOKEN.match(text, pos)
            if not m:
                raise ParseError(text, pos, f"unexpected character {text[pos]!r}")
            kind = m.lastgroup
            self.tokens.append((kind, m.group(kind), m.start(kind)))
            pos = m.end()
        self.tokens.append(("end", "", len(text)))
        self.i = 0

    def peek(self):
        return self.tokens[self.i]

    def take(self):
        t = self.tokens[self.i]
        self.i += 1
        return t

    def fail(self, expected: str):
        kind, value, pos = self.peek()
        found = "the end of the expression" if kind == "end" else repr(value)
        raise ParseError(self.text, pos, f"expected {expected} but found {found}")

    def expect(self, value: str):
        if self.peek()[1] != value or self.peek()[0] != "op":
            self.fail(repr(value))
        self.take()

    def parse(self):
        if self.peek()[0] == "end":
            self.fail("an expression")
        e = self.expr()
        if self.peek()[0] != "end":
            self.fail("an operator or the end of the expression")
        return e

    def expr(self):
        e = self.product()
        while self.peek()[1] in ("+", "-") and self.peek()[0] == "op":
            op = self.take()[1]
            rhs = self.product()
            e = N.add(e, rhs) if op == "+" else N.sub(e, rhs)
        return e

    def product(self):
        e = self.unary()
        while self.peek()[1] in ("*", "/") and self.peek()[0] == "op":
            op = self.take()[1]
            rhs = self.unary()
            e = N.mul(e, rhs) if op == "*" else N.div(e, rhs)
        return e

    def unary(self):
        if self.peek()[0] == "op" and self.peek()[1] in ("-", "+"):
            op = self.take()[1]
            e = self.unary()
            return N.neg(e) if op == "-" else e
        return self.power()

    def power(self):
        base = self.atom()
        if self.peek()[0] == "op" and self.peek()[1] in ("^", "**"):
            self.take()
            pos = self.peek()[2]
            exponent = self.unary()
            try:
                return N.power(base, exponent)
            except ValueError as err:
                raise ParseError(self.text, pos, str(err)) from None
        return base

    def atom(self):
        kind, value, pos = self.peek()
        if kind == "num":
            self.take()
            return N.const(float(value))
        if kind == "name":
            self.take()
            if value in ("x", "y", "z"):
                return N.var(value)
            if value in CONSTANTS:
                return N.const(CONSTANTS[value])
            if value in FUNCTIONS:
                return self.call(value, pos)
            known = ", ".join(["x", "y", "z", *CONSTANTS, *FUNCTIONS])
            raise ParseError(self.text, pos, f"unknown identifier {value!r} (known: {known})")
        if kind == "op" and value == "(":
            self.take()
            e = self.expr()
            self.expect(")")
            return e
        self.fail("a number, a variable, a function or '('")

    def call(self, name, pos):
        self.expect("(")
        args = [self.expr()]
        while self.peek()[0] == "op" and self.peek()[1] == ",":
            self.take()
            args.append(self.expr())
        self.expect(")")
        arity = FUNCTIONS[name]
        if (arity == 1 and len(args) != 1) or len(args) < arity:
            need = "1 argument" if arity == 1 else f"at least {arity} arguments"
            raise ParseError(self.text, pos, f"{name}() takes {need}, got {len(args)}")
        return _BUILD[name](*args)


def parse(text: str) -> N.Expr:
    """Parse a string of the expression language into an expression."""
    if not isinstance(text, str):
        raise TypeError(f"parse() takes a string, not {type(text).__name__}")
    return _Parser(text).parse()
