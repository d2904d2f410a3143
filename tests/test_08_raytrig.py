"""A sum of products of sines and cosines along a ray as a sum of sinusoids
(:mod:`lgshape.expr.raytrig`): the recognition, the bounds of the forms the
search's test takes, and the search on the gyroid.

Oracles: the expression evaluated in 40-digit decimal arithmetic
(Python's decimal, with sine and cosine by their Taylor series after
reduction by a 60-digit pi) at the exact binary values of the float64 ray
and constants, for F and g = dF/dt; and for the search, a float64 scan of
F along each ray (step 2e-4 of the box diagonal) with bisection."""
import decimal
from decimal import Decimal as Dec

import numpy as np
import pytest

import lgshape
from lgshape.arraymath import NUMPY
from lgshape.expr import ray_derivatives, raytrig
from lgshape.expr.node import topological
from lgshape.expr.quadratic import Segment
from lgshape.reference import clip_to_box
from lgshape.surfaces import LIBRARY

CTX = decimal.Context(prec=40)
PI = Dec("3.14159265358979323846264338327950288419716939937510582097494")

SCHWARZ_D = ("0.8*sin(2*x)*sin(2*y)*sin(2*z) + sin(2*x)*cos(2*y)*cos(2*z)"
             " + cos(2*x)*sin(2*y)*cos(2*z) + cos(2*x)*cos(2*y)*sin(2*z) - 0.3")
SCHWARZ_P = "cos(3*x + 0.5) + cos(3*y) + cos(3*z - 1/3)"


def _sin(x):
    with decimal.localcontext(CTX):
        x = x - 2 * PI * (x / (2 * PI)).to_integral_value()
        term, out, k = x, x, 1
        while abs(term) > Dec("1e-45"):
            term = -term * x * x / ((2 * k) * (2 * k + 1))
            out += term
            k += 1
        return out


def _cos(x):
    with decimal.localcontext(CTX):
        return _sin(x + PI / 2)


def _decimal(f, env):
    """f's value in 40-digit decimal arithmetic (env: name -> Decimal)."""
    val = {}
    with decimal.localcontext(CTX):
        for n in topological([f]):
            a = [val[id(x)] for x in n.args]
            op = n.op
            if op == "var":
                v = env[n.param]
            elif op == "const":
                v = Dec(n.param)
            elif op == "named":
                v = Dec(n.param[1])
            elif op == "add":
                v = a[0] + a[1]
            elif op == "sub":
                v = a[0] - a[1]
            elif op == "mul":
                v = a[0] * a[1]
            elif op == "div":
                v = a[0] / a[1]
            elif op == "neg":
                v = -a[0]
            elif op == "pow":
                v = a[0] ** int(n.param)
            elif op == "sin":
                v = _sin(a[0])
            elif op == "cos":
                v = _cos(a[0])
            else:
                raise ValueError(op)
            val[id(n)] = v
    return val[id(f)]


def test01_recognised():
    """The gyroid (three products of two factors) is six sinusoids along a
    ray; Schwarz's P three; D (four products of three factors and a
    constant) sixteen. Not such a sum: a power of a sine, a sine of a
    product, a term without a sine or cosine."""
    T = raytrig.trig_sum(LIBRARY["gyroid"]().expr)
    assert len(T.sinusoids) == 6 and len(T.args) == 3
    assert len(raytrig.trig_sum(lgshape.parse(SCHWARZ_P)).sinusoids) == 3
    assert len(raytrig.trig_sum(lgshape.parse(SCHWARZ_D)).sinusoids) == 16
    for f in ("sin(x)^2 + cos(y)", "sin(x*y) + cos(z)", "x + sin(y)", "x^3 - y"):
        assert raytrig.trig_sum(lgshape.parse(f)) is None, f
    assert lgshape.Surface(LIBRARY["gyroid"]()).ray_trig is not None


def _random_rays(name, n, rng):
    """f, g = dF/dt, f's TrigSum and n random rays (e in the box, unit d,
    t in [-2, 2]) with their sinusoids (float64)."""
    f = {"gyroid": LIBRARY["gyroid"]().expr, "schwarz_p": lgshape.parse(SCHWARZ_P),
         "schwarz_d": lgshape.parse(SCHWARZ_D)}[name]
    g, _ = ray_derivatives(f)
    T = raytrig.trig_sum(f)
    e = rng.uniform(-1.5, 1.5, (n, 3))
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t = rng.uniform(-2, 2, n)
    return f, g, T, e, d, t, raytrig.ray_sinusoids(T, list(e.T), list(d.T), NUMPY)


@pytest.mark.parametrize("name", ["gyroid", "schwarz_p", "schwarz_d"])
def test02_forms_enclose_the_exact_values(name, rng):
    """On random rays (float64), at random t and half widths r from 1e-6
    to 0.3: F(t) within the bound eF of the exact value, and the exact F
    and g at 17 points of [t - r, t + r] (ends included) inside F's and
    g's forms (c0 + c1 s + c2 s^2 within R, evaluated exactly). The bounds
    are not vacuous: the largest error reaches 1e-3 of its bound."""
    n = 40
    f, g, T, e, d, t, R = _random_rays(name, n, rng)
    r = 10.0 ** rng.uniform(-6, np.log10(0.3), n)
    seg = Segment(NUMPY, r)
    Qf, Qg, F, eF = raytrig.forms(seg, R, t, T.sinusoids)
    worst = 0.0
    for i in range(n):
        E, D = [Dec(float(v)) for v in e[i]], [Dec(float(v)) for v in d[i]]

        def at(tt):
            env = {v: E[a] + tt * D[a] for a, v in enumerate("xyz")}
            env.update({"d" + v: D[a] for a, v in enumerate("xyz")})
            return _decimal(f, env), _decimal(g, env)
        ti = Dec(float(t[i]))
        exact_F, _ = at(ti)
        err = abs(exact_F - Dec(float(F[i])))
        assert err <= Dec(float(eF[i])), (i, err, eF[i])
        worst = max(worst, float(err) / float(eF[i]))
        for s in np.linspace(-1.0, 1.0, 17) * float(seg.r[i]):
            s = Dec(float(s))
            vF, vg = at(ti + s)
            for Q, v, what in ((Qf, vF, "F"), (Qg, vg, "g")):
                q = Dec(float(Q.c0[i])) + Dec(float(Q.c1[i])) * s + Dec(float(Q.c2[i])) * s * s
                assert abs(v - q) <= Dec(float(Q.R[i])), (what, i, float(s), abs(v - q), Q.R[i])
    assert worst > 1e-3, worst


def test03_gyroid_search_against_a_scan(rng):
    """The search on the gyroid (each ray's sinusoids) against a float64
    scan of F along each ray (step 2e-4 of the box diagonal, bisected):
    rays from around the box towards it, and from inside it. A hit: F
    changes sign within the tolerance (1e-6 diag) about t, and the scan
    finds no sign change before t - tol; a miss: the scan finds none on
    the whole ray. (A pair of roots closer than the step escapes the scan;
    random rays rarely make one, and such a ray would show here as a hit
    before the scan's first root.)"""
    spec = LIBRARY["gyroid"]()
    surf = lgshape.Surface(spec)
    assert surf.ray_trig is not None
    lo, hi = np.asarray(spec.bbox[0]), np.asarray(spec.bbox[1])
    diag = float(np.linalg.norm(hi - lo))
    n = 1500
    centre = 0.5 * (lo + hi)
    far = rng.normal(size=(n, 3))
    far = centre + 0.75 * diag * far / np.linalg.norm(far, axis=1, keepdims=True)
    aim = lo + (hi - lo) * rng.uniform(0.1, 0.9, (n, 3))
    inside = lo + (hi - lo) * rng.uniform(0, 1, (n, 3))
    d2 = rng.normal(size=(n, 3))
    o = np.concatenate([far, inside]).astype(np.float32)
    d = np.concatenate([aim - far, d2])
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    res = surf.trace(o, d)
    hit, t64 = np.asarray(res.hit), np.asarray(res.t64)
    assert not np.asarray(res.capped).any()
    f = spec.expr

    def F(p):
        return np.broadcast_to(lgshape.expr.evaluate(f, {v: p[..., i] for i, v in enumerate("xyz")}),
                               p.shape[:-1])
    O, D = o.astype(np.float64), d.astype(np.float64)
    t0, t1 = clip_to_box(O, D, lo, hi)
    tol = 1e-6 * diag
    step = 2e-4 * diag
    first = np.full(len(O), np.inf)
    for i in np.nonzero(t1 > t0)[0]:
        ts = np.arange(t0[i], t1[i] + step, step)
        ts[-1] = min(ts[-1], t1[i])
        v = F(O[i] + ts[:, None] * D[i])
        ch = np.nonzero(np.sign(v[:-1]) * np.sign(v[1:]) <= 0)[0]
        if len(ch):
            first[i] = ts[ch[0]]            # the step holding the first root starts here
    miss = ~hit
    assert np.all(np.isinf(first[miss])), f"{int(np.isfinite(first[miss]).sum())} misses cross"
    h = np.nonzero(hit)[0]
    assert np.all(t64[h] <= first[h] + step + tol), "a hit after the scan's first root"
    a = F(O[h] + (t64[h] - tol)[:, None] * D[h])
    b = F(O[h] + (t64[h] + tol)[:, None] * D[h])
    assert np.all(np.sign(a) * np.sign(b) <= 0), "a hit without a sign change about it"
    assert np.all(np.isfinite(first[h])), "a hit where the scan finds no root"
    assert hit.sum() > 1000 and miss.sum() > 100, (hit.sum(), miss.sum())


@pytest.mark.parametrize("name", ["gyroid", "schwarz_p", "schwarz_d"])
def test04_newton_values(name, rng):
    """The values Newton's steps take (:func:`raytrig.value_and_slope`,
    float64): F(t) and F'(t) within 1e-12 of the exact ones, relative to
    the sum of the amplitudes (and times the frequencies). Oracle: f and g
    in 40-digit decimal arithmetic at the float64 ray's exact values."""
    n = 30
    f, g, T, e, d, t, R = _random_rays(name, n, rng)
    F, G = raytrig.value_and_slope(NUMPY, R, t, T.sinusoids)
    amp = np.broadcast_to(sum(np.abs(A) for A in R.A), (n,))
    amp1 = np.broadcast_to(sum(np.abs(A * w) for A, w in zip(R.A, R.omega)), (n,))
    for i in range(n):
        E, D = [Dec(float(v)) for v in e[i]], [Dec(float(v)) for v in d[i]]
        tt = Dec(float(t[i]))
        env = {v: E[a] + tt * D[a] for a, v in enumerate("xyz")}
        env.update({"d" + v: D[a] for a, v in enumerate("xyz")})
        assert abs(float(_decimal(f, env)) - F[i]) <= 1e-12 * amp[i]
        assert abs(float(_decimal(g, env)) - G[i]) <= 1e-12 * amp1[i]
