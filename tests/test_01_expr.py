"""The expression language: parser, Python operators, printer, errors.

Oracle: the same function written three ways (a string, Python operators,
plain numpy code) gives the same float64 values at random points."""
import math
import re

import numpy as np
import pytest

import lgshape
from lgshape import ParseError, parse, x, y, z
from lgshape.expr import evaluate
from lgshape.expr.printer import to_string
from lgshape.surfaces import LIBRARY

PAIRS = [
    ("x^4 - 5*x^2 + y^4 - 5*y^2 + z^4 - 5*z^2 + 11.8",
     x**4 - 5 * x**2 + y**4 - 5 * y**2 + z**4 - 5 * z**2 + 11.8,
     lambda X, Y, Z: X**4 - 5 * X**2 + Y**4 - 5 * Y**2 + Z**4 - 5 * Z**2 + 11.8),
    ("-x^2 + 2**3*y - z/(1+x*x)", -x**2 + 2**3 * y - z / (1 + x * x),
     lambda X, Y, Z: -X**2 + 8 * Y - Z / (1 + X * X)),
    ("sqrt(x*x + y*y + 1) - exp(-z) + log(2 + sin(x)) * cos(y)",
     lgshape.sqrt(x * x + y * y + 1) - lgshape.exp(-z) + lgshape.log(2 + lgshape.sin(x)) * lgshape.cos(y),
     lambda X, Y, Z: np.sqrt(X * X + Y * Y + 1) - np.exp(-Z) + np.log(2 + np.sin(X)) * np.cos(Y)),
    ("abs(x) + min(x, y, z) - max(y, 2*z) + x^-2 + pi*e",
     abs(x) + lgshape.minimum(x, y, z) - lgshape.maximum(y, 2 * z) + x**-2 + np.pi * np.e,
     lambda X, Y, Z: np.abs(X) + np.minimum(np.minimum(X, Y), Z) - np.maximum(Y, 2 * Z) + X**-2.0 + np.pi * np.e),
    ("2^2^3 + .5e1*x - 1.5E-1", 2**(2**3) + 5 * x - 0.15, lambda X, Y, Z: 256 + 5 * X - 0.15),
]


@pytest.mark.parametrize("text,built,reference", PAIRS)
def test01_parse_matches_operators_and_numpy(text, built, reference, rng):
    P = rng.uniform(-2, 2, (3, 500))
    env = dict(zip("xyz", P))
    parsed = parse(text)
    assert parsed is built                                   # interned: the same DAG
    np.testing.assert_allclose(evaluate(parsed, env), reference(*P), rtol=1e-12)


@pytest.mark.parametrize("name", sorted(LIBRARY))
def test02_printer_round_trips(name, rng):
    e = LIBRARY[name]().expr
    back = parse(to_string(e))
    P = dict(zip("xyz", rng.uniform(-1, 1, (3, 200))))
    np.testing.assert_allclose(evaluate(back, P), evaluate(e, P), rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("text,pos,fragment", [
    ("x +", 4, "expected a number"),
    ("2*(x - y", 9, "expected ')'"),
    ("x y", 3, "expected an operator"),
    ("sin(x, y)", 1, "sin() takes 1 argument"),
    ("x ^ 0.5", 5, "only integer powers"),
    ("x ^ y", 5, "constant integer"),
    ("x $ 1", 3, "unexpected character '$'"),
    ("", 1, "expected an expression"),
    ("max(x)", 1, "at least 2 arguments"),
])
def test03_errors_name_the_position(text, pos, fragment):
    with pytest.raises(ParseError) as err:
        parse(text)
    assert err.value.pos + 1 == pos
    assert f"at position {pos}" in str(err.value)
    assert fragment in str(err.value)


def test04_unknown_identifier_is_named():
    with pytest.raises(ParseError, match=r"unknown identifier 'w'.*position 7"):
        parse("x + 2*w")
    with pytest.raises(ParseError, match="unknown identifier 'step'"):
        parse("step(x)")   # internal op, not part of the language


def test05_shared_subexpressions():
    a = (x * y + 1) ** 2
    e = a + lgshape.sin(a) + a * z
    # x, y, 1, x*y, x*y+1, a, sin(a), z, a*z and two additions.
    assert e.size() == 11


def test06_bad_python_values():
    with pytest.raises(ValueError, match="integer powers"):
        x ** 1.5
    with pytest.raises(TypeError):
        x + "1"
    with pytest.raises(ValueError, match="not finite"):
        x + float("inf")


@pytest.mark.parametrize("text,pos", [
    ("1e400*x", 1),
    ("x + 2*1e400", 7),
    ("x ^ 1e999", 5),
    ("sin(x) - 1" + "0" * 400, 10),      # an integer literal beyond float64
    ("min(x, .5e309)", 8),
])
def test07_number_beyond_float64_names_its_position(text, pos):
    """Oracle: the literal's own position (1-based) in the text, and the
    ParseError's message naming it; a raw ValueError was raised before."""
    with pytest.raises(ParseError) as err:
        parse(text)
    assert err.value.pos + 1 == pos
    assert f"at position {pos}" in str(err.value)
    assert "too large for a float64" in str(err.value)
    assert parse(text.replace("1e400", "1e300").replace("1e999", "2").replace(".5e309", ".5e308")
                 .replace("0" * 400, "0")) is not None   # the same text with a finite literal


def test08_non_finite_python_constants_are_refused():
    """Oracle: math.isfinite; the message says why."""
    for bad in (float("inf"), -float("inf"), float("nan"), 10**400):
        with pytest.raises(ValueError, match="is not finite.*finite float64"):
            x * bad
        with pytest.raises(ValueError, match="not finite"):
            lgshape.Expr.lift(bad)
    with pytest.raises(ValueError, match="integer powers"):
        x ** float("inf")
    assert (x ** 2**70).param == 2**70


def test09_long_text_errors_quote_an_excerpt():
    """An error far into a long text names the exact position; the message
    quotes the 160 characters around it, the caret under the culprit."""
    text = "x + " * 5000 + "$ + y"
    with pytest.raises(ParseError) as err:
        parse(text)
    pos = text.index("$")
    assert err.value.pos == pos and f"at position {pos + 1}:" in str(err.value)
    _, shown, caret = str(err.value).split("\n")
    assert len(shown) < 200 and shown[caret.index("^")] == "$"


def test10_min_max_are_balanced_trees():
    """min/max of n arguments: n - 1 binary nodes, ceil(log2 n) deep, the
    arguments left to right (oracle: the pairs written out by hand)."""
    a, b, c, d, e_ = x, y, z, x * y, y * z
    assert lgshape.minimum(a, b, c) is lgshape.minimum(lgshape.minimum(a, b), c)
    assert lgshape.maximum(a, b, c, d) is lgshape.maximum(lgshape.maximum(a, b),
                                                          lgshape.maximum(c, d))
    assert parse("min(x, y, z, x*y, y*z)") is lgshape.minimum(
        lgshape.minimum(lgshape.minimum(a, b), lgshape.minimum(c, d)), e_)
    assert lgshape.minimum(x, x) is x


@pytest.mark.parametrize("f, smaller", [
    ("1 - 4/9*u^3 + 17/9*u^2 - 22/9*u", True),
    ("x^4 - 5*x^2 + y^4 - 5*y^2 + z^4 - 5*z^2 + 11.8", False),
    ("x^4 - 2*x^3 - 5*x^2 + y", True),
    ("2*(x*y)^3 - (x*y)^2 + 3*(x*y) - sin(z) + 0.5*(x*y)", True),
    ("x^2 + y^2 + z^2 - 1", False),
    ("sin(x)*cos(y) + sin(y)*cos(z) + sin(z)*cos(x)", False),
])
def test30_horner_form(f, smaller, rng):
    """lgshape.expr.horner regroups a sum's powers of one subexpression
    (at least two powers, one >= 2, at most one missing below the highest)
    and leaves other sums alone. Oracle:
    the expression as written, evaluated in float64 at random points (the
    same function: equal to rounding), and the node counts."""
    from lgshape.expr.horner import horner
    from lgshape.expr import evaluate
    e = parse(f.replace("u", "(x^2 + y^2 + z^2)"))
    h = horner(e)
    p = rng.uniform(-1.5, 1.5, (3, 2000))
    env = dict(x=p[0], y=p[1], z=p[2])
    v, w = evaluate(e, env), evaluate(h, env)
    assert np.allclose(w, v, rtol=1e-12, atol=1e-12 * np.abs(v).max())
    assert (h.size() < e.size()) if smaller else (h is e)


class _Counting:
    """A compiled pattern whose anchored ``match`` calls are counted, with
    the characters each one consumed."""

    def __init__(self, pattern):
        self.pattern, self.calls, self.consumed = pattern, 0, 0

    def match(self, text, pos):
        m = self.pattern.match(text, pos)
        self.calls += 1
        self.consumed += m.end() - pos
        return m


@pytest.mark.timeout(60)           # a hang guard only: the assertions count operations
@pytest.mark.parametrize("text", ["x^2 + y^2 + z^2 - 1" + " " * 200_000,
                                  " \t\n" * 50_000 + "x" + "\n" * 100_000 + "- 1" + "\u00a0" * 1000,
                                  "+".join(f"{k}.5*x^{k % 5}" for k in range(20_000))])
def test11_tokenizer_reads_each_character_once(text, monkeypatch):
    """The tokenizer is linear in the text, trailing white space included:
    two anchored matches per token (its leading white space, then the
    token), and together they consume every character exactly once. Oracle:
    the counts (tokens from a plain split of the same text), not a clock."""
    from lgshape.expr import parser as P
    space, token = _Counting(P._SPACE), _Counting(P._TOKEN)
    monkeypatch.setattr(P, "_SPACE", space)
    monkeypatch.setattr(P, "_TOKEN", token)
    tokens = P._tokenize(text)
    assert token.calls == len(tokens) - 1 and space.calls == len(tokens)
    assert space.consumed + token.consumed == len(text)
    assert [v for _, v, _ in tokens[:-1]] == [v for v in re.findall(
        r"\d+\.?\d*(?:[eE][+-]?\d+)?|\.\d+|[A-Za-z_]\w*|\*\*|[-+*/^(),]", text)]
    monkeypatch.undo()
    parse(text)                     # and the whole text parses


def test12_like_terms_fold_exactly():
    """x + x + ... + x (n terms) is one term n*x, and c1*t + c2*t is
    (c1 + c2)*t where that sum is exact in float64 (else kept as written,
    so the real value never changes). Oracle: exact rational arithmetic
    (fractions.Fraction) on the coefficients."""
    from fractions import Fraction
    f = parse("+".join(["x"] * 2001) + "-1")
    assert f.op == "sub" and f.args[0].op == "mul" and f.args[0].args[0].param == 2001.0
    e = parse("sin(x) + sin(x) - 3*sin(x)")           # (1 + 1 - 3) sin(x): -sin(x)
    assert e.op == "neg" and e.args[0] is parse("sin(x)")
    for a, b in [(0.1, 0.2), (0.5, 0.25), (1e308, 1e308), (3.0, -3.0), (2.0**-1074, 1.0),
                 (1e16, 1.0), (0.75, 2.0**-60)]:
        e = parse(f"{a!r}*y + {b!r}*y")
        exact = Fraction(a) + Fraction(b)
        if e.op == "mul":
            assert Fraction(e.args[0].param) == exact
        elif e.op == "const":
            assert e.param == 0.0 and exact == 0
        else:                      # kept: the float64 sum is inexact or overflows
            assert e.op == "add"
            assert not math.isfinite(a + b) or Fraction(a + b) != exact
