"""Parser for the expression language (the same language the Python
operators build).

Grammar (whitespace is ignored; ``^`` and ``**`` are the same)::

    expr    := product (('+' | '-') product)*
    product := unary (('*' | '/') unary)*
    unary   := ('-' | '+') unary | power
    power   := atom (('^' | '**') unary)?        exponent: a constant integer
    atom    := NUMBER | NAME | NAME '(' expr (',' expr)* ')' | '(' expr ')'
    NAME    := x | y | z | pi | e | a function name | a bound constant
    NUMBER  := 12 | 1.5 | .5 | 1e-3 | 2.5E+2      (a finite float64)

Functions: sqrt, exp, log, sin, cos, abs (one argument), min, max (two or
more). ``-x^2`` is ``-(x^2)``; ``x^2^3`` is ``x^(2^3)``. Errors are
:class:`ParseError`, which names the position and what was expected.

Named constants: ``parse(text, constants={"radius": 0.5})`` reads the
identifier ``radius`` as the constant 0.5 (exactly as if the number had been
written there). Any other identifier that is not a variable, ``pi``, ``e``
or a function is an error naming it (:attr:`ParseError.identifier`).
:func:`free_names` lists the identifiers of a text that need such a binding.

The parser is iterative, so neither the length of the text nor its nesting
depth is limited by Python's recursion limit: it is the recursive descent of
the grammar above with the call stack made explicit. One loop reads a unary
(its prefix signs become pending frames, then an atom; an opening
parenthesis or function call pushes a frame and starts over inside it), then
reduces: a following ``^`` pushes a power frame and reads the exponent;
otherwise the pending signs and powers apply, then a pending ``*``/``/`` and
``+``/``-`` (one of each at most: they are combined as soon as their right
operand is complete, which keeps them left-associative), and a complete
expression closes a parenthesis, a call argument or the text. It builds the
same nodes in the same order, and fails at the same token with the same
message, as the recursive version did. Time and memory are linear in the
length of the text (the tokenizer too, whitespace included: :func:`_tokenize`).
"""
from __future__ import annotations

import math
import numbers
import re

from . import node as N
from .ops import CONSTANTS, FUNCTIONS

# One token (matched where the whitespace before it ends); `bad` catches a
# character no token starts with.
_TOKEN = re.compile(r"(?P<num>(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)|(?P<name>[A-Za-z_]\w*)"
                    r"|(?P<op>\*\*|[-+*/^(),])|(?P<bad>\S)")
_SPACE = re.compile(r"\s*")

_BUILD = {"sqrt": N.sqrt, "exp": N.exp, "log": N.log, "sin": N.sin, "cos": N.cos,
          "abs": N.abs_, "min": N.minimum, "max": N.maximum}
assert set(_BUILD) == set(FUNCTIONS), "parser and op table disagree"

_VARIABLES = ("x", "y", "z")
_NAME = re.compile(r"[A-Za-z_]\w*")

# Frames of the explicit parse stack (the pending calls of the recursive
# descent), as tuples whose first item is one of:
_ROOT = 0    # (_ROOT,)                       the whole text: expects the end
_PAREN = 1   # (_PAREN,)                      '(' expr  -- expects ')'
_CALL = 2    # (_CALL, name, pos, args)       name '(' expr, ... -- ',' or ')'
_SUM = 3     # (_SUM, lhs, op)                lhs '+'|'-'  -- waits for a product
_PROD = 4    # (_PROD, lhs, op)               lhs '*'|'/'  -- waits for a unary
_NEG = 5     # (_NEG,)                        '-'          -- waits for a unary
_POW = 6     # (_POW, base, pos)              base '^'     -- waits for a unary
#                                             (pos: the exponent's, for errors)
# _NEG and _POW are the largest: a completed unary pops every frame >= _NEG.


_SHOWN = 160   # a longer text is shown as an excerpt around the error


class ParseError(ValueError):
    """A malformed expression; ``pos`` is the 0-based character position.
    The message quotes the text with a caret under that position (for a
    text over 160 characters, the 160 or so around it). ``identifier``: the
    name, for an unknown identifier (else None)."""

    def __init__(self, text: str, pos: int, message: str, identifier: str | None = None):
        self.text, self.pos, self.identifier = text, pos, identifier
        shown, caret = text, pos
        if len(text) > _SHOWN:
            start = max(0, min(pos - _SHOWN // 2, len(text) - _SHOWN))
            end = start + _SHOWN
            shown = ("..." if start else "") + text[start:end] + ("..." if end < len(text) else "")
            caret = pos - start + (3 if start else 0)
        super().__init__(f"{message} at position {pos + 1}:\n  {shown}\n  {' ' * caret}^")


def _tokenize(text: str) -> list:
    """The tokens of ``text``: [(kind, value, position), ..., ("end", "", len)].

    Linear in the length of the text: two anchored matches per token (its
    leading whitespace, then the token), each reading only the characters it
    consumes and one more, so every character is read a bounded number of
    times. (A search for a token preceded by optional whitespace, as this
    once was, rescans a run of trailing whitespace from each of its
    positions: quadratic in its length.)"""
    tokens = []
    append = tokens.append
    space, token = _SPACE.match, _TOKEN.match
    pos, n = 0, len(text)
    while True:
        pos = space(text, pos).end()
        if pos >= n:
            break
        m = token(text, pos)            # never None: `bad` takes any non-space
        kind = m.lastgroup
        if kind == "bad":
            raise ParseError(text, pos, f"unexpected character {text[pos]!r}")
        append((kind, m.group(kind), pos))
        pos = m.end()
    append(("end", "", n))
    return tokens


def _short(token: str) -> str:
    """A token as messages quote it: long names and numbers are cut."""
    return token if len(token) <= 40 else f"{token[:24]}...{token[-12:]}"


def _number(text: str, value: str, pos: int) -> N.Expr:
    v = float(value)          # never raises on what the tokenizer accepts
    if not math.isfinite(v):  # 1e400, or an integer literal of 309+ digits
        raise ParseError(text, pos, f"number {_short(value)} is too large for a float64 "
                         f"(the largest is about 1.8e308)")
    return N.const(v)


def _is_builtin(name: str) -> bool:
    return name in _VARIABLES or name in CONSTANTS or name in FUNCTIONS


class _Parser:
    def __init__(self, text: str, constants: dict):
        self.text = text
        self.constants = constants
        self.tokens = _tokenize(text)
        self.i = 0

    def fail(self, expected: str):
        kind, value, pos = self.tokens[self.i]
        found = "the end of the expression" if kind == "end" else repr(_short(value))
        raise ParseError(self.text, pos, f"expected {expected} but found {found}")

    def expect(self, value: str):
        kind, v, _ = self.tokens[self.i]
        if v != value or kind != "op":
            self.fail(repr(value))
        self.i += 1

    def parse(self) -> N.Expr:
        if self.tokens[0][0] == "end":
            self.fail("an expression")
        text, tokens = self.text, self.tokens
        stack = [(_ROOT,)]
        push, pop = stack.append, stack.pop
        while True:
            # -- a unary: prefix signs, then an atom ----------------------
            kind, value, pos = tokens[self.i]
            while kind == "op" and (value == "-" or value == "+"):
                if value == "-":
                    push((_NEG,))
                self.i += 1
                kind, value, pos = tokens[self.i]
            if kind == "num":
                self.i += 1
                e = _number(text, value, pos)
            elif kind == "name":
                self.i += 1
                if value in _VARIABLES:
                    e = N.var(value)
                elif value in CONSTANTS:
                    e = N.const(CONSTANTS[value])
                elif value in FUNCTIONS:
                    self.expect("(")
                    push((_CALL, value, pos, []))
                    continue                       # parse the first argument
                elif value in self.constants:
                    e = self.constants[value]
                else:
                    known = ", ".join([*_VARIABLES, *CONSTANTS, *FUNCTIONS])
                    if self.constants:
                        known += "; bound constants: " + ", ".join(map(_short, self.constants))
                    raise ParseError(text, pos,
                                     f"unknown identifier {_short(value)!r} (known: {known})",
                                     identifier=value)
            elif kind == "op" and value == "(":
                self.i += 1
                push((_PAREN,))
                continue                           # parse the inner expr
            else:
                self.fail("a number, a variable, a function or '('")

            # -- e is a complete atom: reduce as far as the grammar allows --
            while True:
                # power := atom ('^' unary)?
                kind, value, _ = tokens[self.i]
                if kind == "op" and (value == "^" or value == "**"):
                    self.i += 1
                    push((_POW, e, tokens[self.i][2]))
                    break                          # parse the exponent (a unary)
                # e is a complete unary: apply the pending signs and powers
                top = stack[-1]
                while top[0] >= _NEG:
                    pop()
                    if top[0] == _NEG:
                        e = N.neg(e)
                    else:
                        try:
                            e = N.power(top[1], e)
                        except ValueError as err:
                            raise ParseError(text, top[2], str(err)) from None
                    top = stack[-1]
                # product := unary (('*' | '/') unary)*
                if top[0] == _PROD:
                    pop()
                    e = N.mul(top[1], e) if top[2] == "*" else N.div(top[1], e)
                    top = stack[-1]
                kind, value, _ = tokens[self.i]
                if kind == "op" and (value == "*" or value == "/"):
                    self.i += 1
                    push((_PROD, e, value))
                    break                          # parse the next factor
                # expr := product (('+' | '-') product)*
                if top[0] == _SUM:
                    pop()
                    e = N.add(top[1], e) if top[2] == "+" else N.sub(top[1], e)
                    top = stack[-1]
                if kind == "op" and (value == "+" or value == "-"):
                    self.i += 1
                    push((_SUM, e, value))
                    break                          # parse the next term
                # e is a complete expr: it closes a parenthesis, an argument
                # or the whole text
                if top[0] == _PAREN:
                    self.expect(")")
                    pop()
                    continue                       # (expr) is an atom
                if top[0] == _CALL:
                    _, name, call_pos, args = top
                    args.append(e)
                    if kind == "op" and value == ",":
                        self.i += 1
                        break                      # parse the next argument
                    self.expect(")")
                    pop()
                    arity = FUNCTIONS[name]
                    if (arity == 1 and len(args) != 1) or len(args) < arity:
                        need = "1 argument" if arity == 1 else f"at least {arity} arguments"
                        raise ParseError(text, call_pos,
                                         f"{name}() takes {need}, got {len(args)}")
                    e = _BUILD[name](*args)
                    continue                       # name(args) is an atom
                # _ROOT
                if kind != "end":
                    self.fail("an operator or the end of the expression")
                return e


def parse(text: str, constants=None) -> N.Expr:
    """Parse a string of the expression language into an expression.

    ``constants``: optional mapping of identifier -> finite number; each such
    identifier in the text stands for that constant. Names of variables,
    ``pi``, ``e`` and functions cannot be bound (ValueError)."""
    if not isinstance(text, str):
        raise TypeError(f"parse() takes a string, not {type(text).__name__}")
    bound = {}
    for name, value in (constants or {}).items():
        if not isinstance(name, str) or not _NAME.fullmatch(name):
            raise ValueError(f"constant name {name!r} is not an identifier")
        if _is_builtin(name):
            raise ValueError(f"constant name {name!r} is a variable, constant or function "
                             "of the expression language and cannot be bound")
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise ValueError(f"constant {name!r} must be a number, got {value!r}")
        try:
            bound[name] = N.named(name, value)
        except ValueError as err:
            raise ValueError(f"constant {name!r}: {err}") from None
    return _Parser(text, bound).parse()


def free_names(text: str) -> list:
    """The identifiers of ``text`` that are neither variables (x, y, z),
    constants (pi, e) nor function names: ``[(name, position), ...]`` in
    order of first appearance (0-based position). These are the names
    :func:`parse` needs bound in ``constants``. Raises :class:`ParseError`
    for a character no token starts with."""
    if not isinstance(text, str):
        raise TypeError(f"free_names() takes a string, not {type(text).__name__}")
    seen = {}
    for kind, value, pos in _tokenize(text):
        if kind == "name" and not _is_builtin(value) and value not in seen:
            seen[value] = pos
    return list(seen.items())
