"""A polynomial f along a ray as a polynomial in the ray parameter
(:mod:`lgshape.expr.raypoly`): coefficients, their error bounds, the shift
to another point and the quadratic forms the search's test takes.

Oracle: exact rational arithmetic (Python fractions): the expression is
expanded along the ray from the exact binary values of the ray's float64
origin and direction and of its constants, so every float64 result and
every bound is checked against the exact polynomial."""
import math
from fractions import Fraction as Fr

import numpy as np
import pytest

import lgshape
from lgshape.arraymath import NUMPY
from lgshape.expr import raypoly
from lgshape.expr.node import topological
from lgshape.expr.quadratic import Segment, quad_range
from lgshape.surfaces import LIBRARY

POLYNOMIALS = ["torus", "tangle", "barth_sextic", "kummer", "chmutov6", "clebsch"]
WRITTEN = ["x^3 - y*z/3 + 0.1*x^2*y - 1/7", "(x - 0.3)^2 * (y + 1/3)^3 - z^5 / 11 + sqrt(2)*x*y*z",
           "-(x*y - z)^4 + 2.5", "(x*y - sqrt(2)*z)^3 / sqrt(2) + x - 1/sqrt(2)"]


def _exact(f, e, d, sqrt_digits=0):
    """F(s) = f(e + s d) exactly: coefficients (fractions), from the exact
    values of e, d and of the constants (float64); with ``sqrt_digits``,
    the square root of a constant to that many decimal digits (rounded
    down)."""
    val = {}

    def mul(a, b):
        c = [Fr(0)] * (len(a) + len(b) - 1)
        for i, x in enumerate(a):
            for j, y in enumerate(b):
                c[i + j] += x * y
        return c
    for n in topological([f]):
        args = [val[id(a)] for a in n.args]
        if n.op == "var":
            a = "xyz".index(n.param)
            val[id(n)] = [Fr(float(e[a])), Fr(float(d[a]))]
        elif n.op == "const":
            val[id(n)] = [Fr(n.param)]
        elif n.op == "named":
            val[id(n)] = [Fr(n.param[1])]
        elif n.op in ("add", "sub"):
            k = 1 if n.op == "add" else -1
            m = max(len(args[0]), len(args[1]))
            a, b = (v + [Fr(0)] * (m - len(v)) for v in args)
            val[id(n)] = [x + k * y for x, y in zip(a, b)]
        elif n.op == "neg":
            val[id(n)] = [-x for x in args[0]]
        elif n.op == "mul":
            val[id(n)] = mul(*args)
        elif n.op == "pow":
            r = [Fr(1)]
            for _ in range(int(n.param)):
                r = mul(r, args[0])
            val[id(n)] = r
        elif n.op == "div":
            assert len(args[1]) == 1
            val[id(n)] = [x / args[1][0] for x in args[0]]
        elif n.op == "sqrt" and sqrt_digits:    # of a constant: to that many digits
            (a,) = args[0]
            k = 10 ** sqrt_digits
            val[id(n)] = [Fr(math.isqrt(a.numerator * a.denominator * k * k), a.denominator * k)]
        elif n.op == "sqrt":
            raise LookupError("sqrt")   # (handled by the caller)
        else:
            raise ValueError(n.op)
    return val[id(f)]


def _expr(name):
    return LIBRARY[name]().expr if name in LIBRARY else lgshape.parse(name)


def _shifted(ex, t):
    n = len(ex) - 1
    return [sum(math.comb(k, j) * ex[k] * t ** (k - j) for k in range(j, n + 1))
            for j in range(n + 1)]


@pytest.mark.parametrize("apriori", [True, False])
@pytest.mark.parametrize("name", POLYNOMIALS + WRITTEN[:1] + WRITTEN[2:3])
def test01_coefficients_and_shift_within_their_bounds(name, apriori, rng, monkeypatch):
    """For random rays: |c_k - exact| <= w_k for every coefficient; after a
    shift to a random t, F(t) within W(|t|), and the summed errors of the
    shifted coefficients, weighted by x^k, within W(|t| + x). Both kinds
    of bounds: a priori (``APRIORI``, the default) and running."""
    monkeypatch.setattr(raypoly, "APRIORI", apriori)
    f = _expr(name)
    worst = 0.0
    for _ in range(25):
        e, d, t, x = rng.normal(size=3) * 2, rng.normal(size=3), rng.normal(), abs(rng.normal())
        c, w = raypoly.ray_polynomial(f, list(e), list(d), NUMPY)
        ex = _exact(f, e, d)
        assert len(c) == len(w) == len(ex) == f.degree() + 1
        for ck, wk, xk in zip(c, w, ex):
            err = abs(Fr(float(ck)) - xk)
            assert err <= Fr(float(wk)), (name, float(err), float(wk))
            worst = max(worst, float(err) / float(wk)) if wk > 0 else worst
        cs, W = raypoly.shift(NUMPY, c, w, np.float64(t))
        exs = _shifted(ex, Fr(t))
        assert abs(Fr(float(cs[0])) - exs[0]) <= Fr(float(raypoly.bound(NUMPY, W, abs(t))))
        total = sum(abs(Fr(float(a)) - b) * Fr(x) ** j for j, (a, b) in enumerate(zip(cs, exs)))
        assert total <= Fr(float(raypoly.bound(NUMPY, W, np.float64(abs(t) + x))))
    assert worst > 1e-3                 # the bounds are not vacuous: errors are met


@pytest.mark.parametrize("apriori", [True, False])
@pytest.mark.parametrize("text", WRITTEN[1:2] + WRITTEN[3:])
def test02_constant_subexpressions(text, apriori, monkeypatch):
    """sqrt(2) in a polynomial (a factor, a divisor; folded to a float64
    literal when the expression is built, so exact by definition there):
    the coefficients enclose the polynomial for sqrt(2) rounded either way
    by one ulp (oracle: exact expansion). Both kinds of bounds (test01).
    The constants' own errors: test02b, test02c."""
    monkeypatch.setattr(raypoly, "APRIORI", apriori)
    f = _expr(text)
    e, d = [0.3, -0.7, 1.1], [0.6, 0.2, -0.9]
    c, w = raypoly.ray_polynomial(f, e, d, NUMPY)
    root2 = math.sqrt(2)
    for r2 in (np.nextafter(root2, 0), np.nextafter(root2, 3)):
        g = lgshape.parse(text.replace("sqrt(2)", repr(float(r2))))
        ex = _exact(g, e, d)
        for ck, wk, xk in zip(c, w, ex):
            assert abs(Fr(float(ck)) - xk) <= Fr(float(wk))


@pytest.mark.parametrize("apriori", [True, False])
@pytest.mark.parametrize("text", [
    "(x^2 + y^2 + z^2 + R^2 - r^2)^2 - 4 * R^2 * (x^2 + y^2)",
    "(x + r^2) * (y - R * r)^3 + (z / r - 1)^2 * x",
    "x^2 + y^2 + z^2 - r^2", "x * y * z - R * r", "x - 2 * R * r"])
def test02c_named_parameters(text, apriori, rng, monkeypatch):
    """Polynomials of scene parameters (named constants, not folded: their
    products are constants computed with error bounds, mixed with the
    ray's terms at every degree): every coefficient within its bound
    (oracle: exact rationals from the parameters' float64 values)."""
    monkeypatch.setattr(raypoly, "APRIORI", apriori)
    f = lgshape.parse(text, {"R": 1.1, "r": 0.3})
    for _ in range(10):
        e, d = rng.normal(size=3) * 2, rng.normal(size=3)
        c, w = raypoly.ray_polynomial(f, list(e), list(d), NUMPY)
        ex = _exact(f, e, d)
        assert len(c) == len(w) == len(ex)
        for ck, wk, xk in zip(c, w, ex):
            assert abs(Fr(float(ck)) - xk) <= Fr(float(wk)), text
        # F(t) after a shift, within W(|t|) (W holds every coefficient's bound)
        t = rng.normal()
        cs, W = raypoly.shift(NUMPY, c, w, np.float64(t))
        assert len(W) == len(c)
        F = _shifted(ex, Fr(t))[0]
        assert abs(Fr(float(cs[0])) - F) <= Fr(float(raypoly.bound(NUMPY, W, abs(t)))), text


@pytest.mark.parametrize("apriori", [True, False])
def test02b_inexact_constant_far_from_its_value(apriori, monkeypatch):
    """A constant subexpression whose float64 value is off by all of it:
    sqrt(k) - 1.4142135623730951 with the parameter k = 2 (a named
    constant: not folded) is 0 in float64 and -9.7e-17 exactly, here times
    1e16, and a divisor sqrt(k): the coefficients' bounds come from the
    constants' error bounds, not from the roundings (oracle: the exact
    expansion with sqrt(2) to 60 digits)."""
    monkeypatch.setattr(raypoly, "APRIORI", apriori)
    f = lgshape.parse("(sqrt(k) - 1.4142135623730951) * 1e16 * (x*y - z)^2 / sqrt(k) + x",
                      {"k": 2.0})
    e, d = [0.3, -0.7, 1.1], [0.6, 0.2, -0.9]
    c, w = raypoly.ray_polynomial(f, e, d, NUMPY)
    ex = _exact(f, e, d, sqrt_digits=60)
    err0 = abs(Fr(float(c[0])) - ex[0])
    assert err0 > 1                                   # the float64 value is far off
    for ck, wk, xk in zip(c, w, ex):
        assert abs(Fr(float(ck)) - xk) <= Fr(float(wk))
    assert Fr(float(w[0])) < 4 * err0                 # and its bound not vacuous


@pytest.mark.parametrize("name", ["barth_sextic", "chmutov6", "clebsch"])
def test03_forms_enclose_F_and_its_slope(name, rng):
    """The quadratic forms from a shift (:func:`raypoly.forms`) over
    |s| <= r: their ranges hold F(t + s) and F'(t + s) exactly at points
    spread over the segment (oracle: exact evaluation of the exact
    polynomial and its derivative)."""
    f = _expr(name)
    for _ in range(20):
        e, d = rng.normal(size=3), rng.normal(size=3)
        t, r = rng.normal(), 10.0 ** rng.uniform(-4, 0)
        c, w = raypoly.ray_polynomial(f, list(e), list(d), NUMPY)
        cs, W = raypoly.shift(NUMPY, c, w, np.float64(t))
        seg = Segment(NUMPY, np.float64(r))
        Qf, Qg = raypoly.forms(seg, cs, W, np.float64(abs(t)))
        Fi, gi = quad_range(seg, Qf), quad_range(seg, Qg)
        exs = _shifted(_exact(f, e, d), Fr(t))
        for s in np.linspace(-r, r, 9):
            S = Fr(float(s))
            Fv = sum(a * S ** k for k, a in enumerate(exs))
            gv = sum(k * a * S ** (k - 1) for k, a in enumerate(exs) if k)
            assert Fr(float(Fi.lo)) <= Fv <= Fr(float(Fi.hi))
            assert Fr(float(gi.lo)) <= gv <= Fr(float(gi.hi))


def test04_only_polynomials():
    """The search takes a polynomial of degree 3 to MAX_DEGREE this way; a
    quadric, a higher degree, or sqrt, sin, min of x, y, z, are evaluated
    as expressions."""
    assert lgshape.Surface(LIBRARY["torus"]()).ray_polynomial
    for f in ("x^2 + y^2 + z^2 - 1", "x^9 + y - z", "sqrt(x^2 + y^2) - z^3", "min(x^3, y) - z"):
        assert not lgshape.Surface(lgshape.parse(f), ((-1,) * 3, (1,) * 3)).ray_polynomial, f
    with pytest.raises(ValueError, match="polynomial"):
        raypoly.ray_polynomial(lgshape.parse("sin(x) + y^3"), [0.0] * 3, [1.0] * 3, NUMPY)


def _real_roots(ex, span):
    """The real roots in [0, span] of the exact polynomial (float64 roots
    of its coefficients rounded once; complex pairs kept within 1e-7)."""
    c = np.array([float(v) for v in ex])
    while len(c) > 1 and c[-1] == 0:
        c = c[:-1]
    if len(c) < 2:
        return np.array([])
    r = np.roots(c[::-1])
    r = r[np.abs(r.imag) <= 1e-7 * max(1.0, span)].real
    return np.sort(r[(r >= -1e-9 * span) & (r <= span * (1 + 1e-9))])


@pytest.mark.parametrize("steps", [1, 3])
@pytest.mark.parametrize("name", POLYNOMIALS + ["x^2 + y^2 + z^2 - 1"])
def test05_clip_keeps_the_first_root(name, steps, rng):
    """Bezier clipping before the walk (:func:`raypoly.clip_first_root`)
    never moves past the first root on [0, span], and calls a ray free of
    roots only where it has none. Oracle: the real roots of the exact
    polynomial (fractions) in [0, span], from numpy's companion matrix; a
    root within 1e-9 span of the clip counts as kept. Rays: random through
    the unit ball, and (the sphere) tangent rays (a double root) and rays
    from a root (F(0) = 0) or to one (F(span) = 0). Not vacuous: a share of
    the rays without roots (a tenth at least) is proven free, and some
    clips move past a tenth of the way to the first root."""
    f = _expr(name)
    cases = []
    for _ in range(60):
        e = rng.normal(size=3)
        e *= 2.5 / np.linalg.norm(e)
        d = -e / 2.5 + 0.5 * rng.normal(size=3)
        cases.append((e, d, float(rng.uniform(1.0, 6.0))))
    if name.startswith("x^2"):
        for _ in range(10):
            u = rng.normal(size=3); u /= np.linalg.norm(u)
            v = np.cross(u, rng.normal(size=3)); v /= np.linalg.norm(v)
            cases.append((u - 0.7 * v, v, 1.4))       # tangent at u, s = 0.7
            cases.append((u, v + 0.3 * u, 2.0))       # F(0) = 0 (to rounding)
            cases.append((u - 2.0 * v, v, 2.0))       # F(2) = 0: the root at the end
    freed = clipped = no_roots = 0
    for e, d, span in cases:
        c, w = raypoly.ray_polynomial(f, list(e), list(d), NUMPY)
        free, first = raypoly.clip_first_root(NUMPY, np.array(c), np.array(w),
                                              np.float64(span), steps)
        roots = _real_roots(_exact(f, e, d), span)
        if len(roots):
            assert not free, (name, e, d, span, roots)
            assert first <= roots[0] + 1e-9 * span, (name, first, roots[0])
            clipped += first > 0.1 * roots[0]
        else:
            no_roots += 1
            freed += bool(free)
    assert freed >= 0.1 * no_roots and clipped > 0, (freed, no_roots, clipped)


@pytest.mark.parametrize("name", POLYNOMIALS)
def test06_newton_values(name, rng):
    """The values Newton's steps take (:func:`raypoly.value_and_slope`,
    Horner on the coefficients): F(t) within W(|t|) plus Horner's rounding
    of the exact F(t), and F'(t) within 1e-9 of the scale of its terms.
    Oracle: the exact polynomial (fractions)."""
    f = _expr(name)
    for _ in range(20):
        e, d, t = rng.normal(size=3), rng.normal(size=3), rng.normal()
        c, w = raypoly.ray_polynomial(f, list(e), list(d), NUMPY)
        F, g = raypoly.value_and_slope(c, np.float64(t))
        ex = _exact(f, e, d)
        T = Fr(t)
        Fx = sum(a * T ** k for k, a in enumerate(ex))
        gx = sum(k * a * T ** (k - 1) for k, a in enumerate(ex) if k)
        n = len(c) - 1
        scale = sum(abs(float(a)) * abs(t) ** k for k, a in enumerate(c))
        W = [4.0 * (n + 1) * 2.0**-53 * abs(ci) + wi for ci, wi in zip(c, w)]
        assert abs(Fr(float(F)) - Fx) <= Fr(float(raypoly.bound(NUMPY, W, abs(t))
                                                 + 4 * n * 2.0**-53 * scale))
        gscale = sum(k * abs(float(a)) * abs(t) ** (k - 1) for k, a in enumerate(c) if k)
        assert abs(float(g) - float(gx)) <= 1e-9 * gscale
