"""Expressions of any size: 100,000 nodes, nesting 10,000 deep.

Each case is parsed from text, printed back, differentiated (gradient,
Hessian, ray derivatives) and evaluated (numpy float64 points and
intervals; Dr.Jit LLVM float32 on a few points), with no RecursionError at
Python's default recursion limit and in time linear in the size.

Oracles, independent of the DAG and its evaluators:

* ``min`` of n affine arguments: numpy's own ``min`` over the argument values
  (the same float64 operations, so equal exactly); its gradient is the slope
  of the arg-min argument; its interval over a box is the exact minimum over
  the box ends (the function is concave in x).
* nested parentheses and ``sin(sin(...))``: a plain Python loop over numpy
  arrays; the derivatives by the chain rule carried in the same loop.
* a sum of 50,000 distinct terms: ``math.fsum`` of the terms, and of their
  analytic first and second derivatives; the error allowed is the proven
  bound n * u * sum |t_i| of left-to-right summation.
* a chain of 100,000 additions ``x + x*0.5 + ...``: x times ``math.fsum`` of
  the coefficients, exactly (every partial sum fits in 24 bits), in float64
  and in Dr.Jit float32; the derivative folds to that fsum.
* a deep chain cycling through every public op: a loop of numpy calls, with
  forward-mode derivatives (value, first, second) written out per op.

Dr.Jit (float32): drjit-core compiles one kernel per ``dr.eval`` and its
compiler is not linear in the kernel size (a 10,000-deep chain of sin
overflows its C stack: a segmentation fault; 10,000 min nodes with opaque
constants take over a minute to compile), so the test cuts the DAG into pieces of a few hundred nodes
(:func:`_evaluate_in_kernels`: each piece is traced by the library's
:func:`evaluate`, with earlier pieces' results given as variables) and
compares with the float64 oracle at float32 tolerance.
"""
import gc
import math
import time

import numpy as np
import pytest

import drjit as dr
from conftest import JIT_AD

Float = JIT_AD.Float

from lgshape import parse
from lgshape.arraymath import NUMPY
from lgshape.expr import evaluate, evaluate_interval, gradient, hessian, ray_derivatives
from lgshape.expr.node import Expr, topological, var
from lgshape.expr.printer import to_string
from lgshape.interval import Interval

U64 = 2.0 ** -53


def _depth(f) -> int:
    """Longest path from f to a leaf, in nodes (iterative)."""
    depth = {}
    for n in topological([f]):
        depth[id(n)] = 1 + max((depth[id(a)] for a in n.args), default=0)
    return depth[id(f)]


def _points(rng, n=7, lo=-0.9, hi=0.9):
    P = rng.uniform(lo, hi, (3, n))
    return P, dict(zip("xyz", P))


def _ray_env(P, D):
    env = dict(zip("xyz", P))
    env.update(zip(("dx", "dy", "dz"), D))
    return env


def _evaluate_in_kernels(f, env, per_kernel=256):
    """evaluate(f, env) in Dr.Jit, as a sequence of kernels of at most
    `per_kernel` nodes: the nodes (children first) are cut into runs; each
    run is rebuilt with the nodes of earlier runs replaced by variables
    bound to their evaluated values, traced by :func:`evaluate` and
    evaluated. The DAG structure within a run is kept as is (``Expr`` is
    called directly, no simplification)."""
    order = topological([f])
    last_use = {id(f): len(order)}
    for i, n in enumerate(order):
        for a in n.args:
            last_use[id(a)] = i
    env, done = dict(env), {}
    for start in range(0, len(order), per_kernel):
        run, end, new = order[start:start + per_kernel], start + per_kernel, {}
        for n in run:
            if n.args:
                args = tuple(a if not a.args else var(done[id(a)]) if id(a) in done
                             else new[id(a)] for a in n.args)
                new[id(n)] = Expr(n.op, args, n.param)
            else:
                new[id(n)] = n
        outs = [n for n in run if n.args and last_use.get(id(n), -1) >= end or n is f]
        values = evaluate([new[id(n)] for n in outs], env)
        dr.eval(*values)
        for n, v in zip(outs, values):
            done[id(n)] = name = f"_k{len(done)}"
            env[name] = v
    return env[done[id(f)]]


def _drjit_check(f, P, expected, rtol, atol=0.0, per_kernel=256):
    env = {v: Float(P[i]) for i, v in enumerate("xyz")}
    got = _evaluate_in_kernels(f, env, per_kernel).numpy()
    np.testing.assert_allclose(got, np.broadcast_to(expected, got.shape), rtol=rtol, atol=atol)


# -- 1. min with many arguments ---------------------------------------------

def _min_case(n, rng):
    """min(a_0*x + c_0, ..., a_{n-1}*x + c_{n-1}) for n distinct pairs
    (a_i, c_i) on a grid of step 1/500, so constants and products are shared
    and f has about 2n nodes. Returns f, a, c, the points and the argument
    values there (the same float64 operations as the DAG's)."""
    pick = rng.choice(1001 * 1001, n, replace=False)
    a, c = (pick // 1001 - 500) / 500, (pick % 1001 - 500) / 500
    text = "min(" + ", ".join(f"{ai!r}*x + {ci!r}" for ai, ci in zip(a.tolist(), c.tolist())) + ")"
    f = parse(text)
    # A balanced tree: ceil(log2 n) levels of min along its left edge.
    levels, e = 0, f
    while e.op == "min":
        levels, e = levels + 1, e.args[0]
    assert levels == math.ceil(math.log2(n))
    P, env = _points(rng)
    terms = a[:, None] * P[0][None, :] + c[:, None]
    return f, a, c, P, env, terms


@pytest.mark.parametrize("n", [1000, 10_000])
def test01_min_of_many_arguments(n, rng):
    """min of n affine arguments; oracle: numpy's min over the argument
    values (equal exactly), the slope of the arg-min argument for the
    gradient and the ray derivative, and for the interval over a box the
    exact minimum over its ends (f is concave in x)."""
    f, a, c, P, env, terms = _min_case(n, rng)
    gx, gy, gz = gradient(f)
    assert gy.param == 0.0 and gz.param == 0.0
    value, slope = evaluate([f, gx], env)
    np.testing.assert_array_equal(value, terms.min(axis=0))
    best = np.sort(terms, axis=0)
    unique = best[1] - best[0] > 1e-9                          # one arg-min
    want = a[terms.argmin(axis=0)]
    np.testing.assert_allclose(slope[unique], want[unique], rtol=0, atol=1e-13)
    if n <= 1000:   # the second derivatives (0 off the creases) and the ray's
        D = rng.normal(size=(3, P.shape[1]))
        H = [h for row in hessian(f) for h in row]
        g, h, *H = evaluate([*ray_derivatives(f), *H], _ray_env(P, D))
        np.testing.assert_allclose(g[unique], (D[0] * want)[unique], rtol=0, atol=1e-13)
        assert all(np.all(v == 0) for v in (h, *H))
    r = 0.01
    i = evaluate_interval(f, {"x": Interval(P[0] - r, P[0] + r), "y": P[1], "z": P[2]}, NUMPY)
    ends = np.minimum(a[:, None] * (P[0] - r) + c[:, None], a[:, None] * (P[0] + r) + c[:, None])
    true_lo = ends.min(axis=0)
    assert np.all(i.lo <= true_lo) and np.all(i.lo >= true_lo - 1e-12)
    assert np.all(i.hi >= terms.min(axis=0))
    assert parse(to_string(f)) is f
    if n <= 1000:
        _drjit_check(f, P, terms.min(axis=0), rtol=1e-5, atol=1e-6)


def test02_min_of_100000_arguments(rng):
    """min of 100,000 affine arguments: parsed, evaluated (oracle: numpy's
    min, equal exactly) and printed (n - 1 binary mins). Derivatives and
    intervals of this tree are checked at n = 10,000 above, and at 100,000+
    nodes on the sum and the chain below."""
    n = 100_000
    f, a, c, P, env, terms = _min_case(n, rng)
    np.testing.assert_array_equal(evaluate(f, env), terms.min(axis=0))
    assert to_string(f).count("min(") == n - 1


# -- 2. nesting 10,000 deep ---------------------------------------------------

DEPTH = 10_000


def test03_nested_parentheses():
    """10,000 nested parentheses; oracle: a Python loop of the same affine
    steps (v <- v*a_k + b_k) in float64."""
    assert parse("(" * DEPTH + "x" + ")" * DEPTH) is var("x")
    assert parse("-(" * DEPTH + "x" + ")" * DEPTH) is var("x")   # an even number of signs
    k = np.arange(DEPTH)
    a, b = 1 - 1e-4 * (k % 7 + 1), 1e-3 * (k % 5)
    text = "(" * DEPTH + "x" + "".join(f"*{ai!r} + {bi!r})"
                                      for ai, bi in zip(a.tolist(), b.tolist()))
    f = parse(text)
    assert _depth(f) >= DEPTH
    X = np.linspace(-2, 2, 9)
    v = X.copy()
    for ai, bi in zip(a, b):
        v = v * ai + bi if bi else v * ai
    np.testing.assert_allclose(evaluate(f, {"x": X, "y": X, "z": X}), v, rtol=1e-13)
    gx = gradient(f)[0]
    assert gx.op == "const"                                   # folded: prod a_k
    np.testing.assert_allclose(gx.param, math.prod(a), rtol=1e-12)
    assert parse(to_string(f)) is f


def test04_nested_sin():
    """sin(sin(...sin(x)...)) 10,000 deep; oracle: the loop v <- sin(v) in
    numpy, with f' = prod cos(v_k) and f'' by the chain rule in the loop."""
    text = "sin(" * DEPTH + "x" + ")" * DEPTH
    f = parse(text)
    assert f.size() == DEPTH + 1 and _depth(f) == DEPTH + 1
    assert to_string(f) == text and repr(f) == text
    X = np.linspace(-1.5, 1.5, 7)
    v, d1, d2 = X.copy(), np.ones_like(X), np.zeros_like(X)
    for _ in range(DEPTH):
        c, s = np.cos(v), np.sin(v)
        d1, d2 = c * d1, c * d2 - s * d1 * d1
        v = s
    env = {"x": X, "y": X, "z": X}
    np.testing.assert_array_equal(evaluate(f, env), v)       # the same np.sin calls
    gx, gy, gz = gradient(f)
    np.testing.assert_allclose(evaluate(gx, env), d1, rtol=1e-12)
    assert gy.param == 0.0 and gz.param == 0.0
    H = hessian(f)
    np.testing.assert_allclose(evaluate(H[0][0], env), d2, rtol=1e-9, atol=1e-15)
    D = np.array([np.full_like(X, 0.6), np.full_like(X, 0.8), np.zeros_like(X)])
    g, h = evaluate(list(ray_derivatives(f)), _ray_env(np.array([X, X, X]), D))
    np.testing.assert_allclose(g, 0.6 * d1, rtol=1e-12)
    np.testing.assert_allclose(h, 0.36 * d2, rtol=1e-9, atol=1e-15)
    # Intervals: a box around each point contains the point value.
    i = evaluate_interval(f, {"x": Interval(X - 1e-3, X + 1e-3), "y": X, "z": X}, NUMPY)
    assert np.all(i.lo <= v) and np.all(v <= i.hi)
    _drjit_check(f, np.array([X, X, X]), v, rtol=1e-4, per_kernel=100)


# -- 3. a sum of 50,000 distinct terms --------------------------------------

def test05_sum_of_distinct_terms(rng):
    """sum_i a_i * w_i^p_i (w alternating x, y; 50,000 terms); oracle:
    math.fsum of the terms and of their analytic derivatives."""
    n = 50_000
    a = rng.uniform(-1, 1, n)
    p = (np.arange(n) // 2) % 4 + 1
    w = np.arange(n) % 2                                      # 0: x, 1: y
    text = " + ".join(f"{ai!r}*{'xy'[wi]}^{pi}" for ai, wi, pi in zip(a.tolist(), w, p))
    f = parse(text)
    assert f.size() == 3 * n + 7            # a_i, a_i*w^p, + (n - 1); x, y, x^2..4, y^2..4
    P, env = _points(rng, 5)
    t = a[:, None] * P[w] ** p[:, None].astype(float)         # terms (rows) at the points
    d1 = a[:, None] * p[:, None] * P[w] ** (p[:, None] - 1.0)
    d2 = a[:, None] * p[:, None] * (p[:, None] - 1.0) * P[w] ** (p[:, None] - 2.0)

    def fsum(terms, mask=None):
        terms = terms if mask is None else terms[mask]
        return np.array([math.fsum(col) for col in terms.T])

    D = rng.normal(size=(3, 5))
    H = hessian(f)
    value, gx, gy, gz, hxx, hxy, hyy, g, h = evaluate(
        [f, *gradient(f), H[0][0], H[0][1], H[1][1], *ray_derivatives(f)], _ray_env(P, D))
    assert np.all(np.abs(value - fsum(t)) <= n * 2 * U64 * fsum(np.abs(t)))
    for got, var_index in ((gx, 0), (gy, 1)):
        m = w == var_index
        assert np.all(np.abs(got - fsum(d1, m)) <= n * 2 * U64 * fsum(np.abs(d1), m))
    assert gz == 0.0 and hxy == 0.0                          # folded to the constant 0
    assert np.all(np.abs(hxx - fsum(d2, w == 0)) <= n * 4 * U64 * fsum(np.abs(d2), w == 0))
    assert np.all(np.abs(hyy - fsum(d2, w == 1)) <= n * 4 * U64 * fsum(np.abs(d2), w == 1))
    want_g = D[0] * fsum(d1, w == 0) + D[1] * fsum(d1, w == 1)
    want_h = D[0] ** 2 * fsum(d2, w == 0) + D[1] ** 2 * fsum(d2, w == 1)
    scale_g = np.abs(D[0]) * fsum(np.abs(d1), w == 0) + np.abs(D[1]) * fsum(np.abs(d1), w == 1)
    scale_h = D[0] ** 2 * fsum(np.abs(d2), w == 0) + D[1] ** 2 * fsum(np.abs(d2), w == 1)
    assert np.all(np.abs(g - want_g) <= n * 8 * U64 * scale_g)
    assert np.all(np.abs(h - want_h) <= n * 8 * U64 * scale_h)
    # Intervals: a box around each point contains the exact value there.
    box = {"x": Interval(P[0] - 1e-3, P[0] + 1e-3), "y": Interval(P[1] - 1e-3, P[1] + 1e-3),
           "z": P[2]}
    i = evaluate_interval(f, box, NUMPY)
    assert np.all(i.lo <= fsum(t)) and np.all(fsum(t) <= i.hi)
    # Printed back: the terms in order, negative constants in parentheses.
    assert to_string(f) == " + ".join(
        (f"{ai!r}" if ai >= 0 else f"({ai!r})") + "*" + "xy"[wi] + (f"^{pi}" if pi > 1 else "")
        for ai, wi, pi in zip(a.tolist(), w, p))
    # Dr.Jit float32: left-to-right summation errs by at most u32 * sum_k |S_k|
    # (S_k the partial sums), the terms (x rounded to float32, powi, the
    # product) by at most 10 u32 |t_i| each; doubled for the rounding of S_k.
    u32 = 2.0 ** -24
    bound = 2 * u32 * (np.abs(np.cumsum(t, axis=0)).sum(axis=0) + 10 * np.abs(t).sum(axis=0))
    _drjit_check(f, P, fsum(t), rtol=0, atol=float(bound.max()), per_kernel=3 * 64)


# -- 4. a chain of 100,000 additions ----------------------------------------

def test06_long_chain():
    """x + y*0.5 + x*0.25 + y*0.125 + ... (100,000 terms, coefficients
    2^-(i mod 8), the variables alternating, so that no two neighbours are
    like terms that construction would fold into one): a left-deep chain
    100,000 additions deep; oracle: math.fsum of the coefficients of x and
    of y. Every partial sum needs at most 24 bits for these x = y, so
    float64 and Dr.Jit's float32 must both give it exactly."""
    n = 100_000
    coef = [0.5 ** (i % 8) for i in range(1, n)]
    var = ["xy"[i % 2] for i in range(1, n)]
    text = "x" + "".join(f"+{v}*{c!r}" for v, c in zip(var, coef))
    f = parse(text)
    depth, e = 0, f
    while e.op == "add":
        depth, e = depth + 1, e.args[0]
    assert depth == n - 1
    X = np.array([-3.0, -1.5, 0.0, 0.75, 3.0])
    Cx = math.fsum([1.0, *(c for v, c in zip(var, coef) if v == "x")])
    Cy = math.fsum(c for v, c in zip(var, coef) if v == "y")
    s = X * (Cx + Cy)
    np.testing.assert_array_equal(evaluate(f, {"x": X, "y": X}), s)
    gx, gy, gz = gradient(f)
    assert gx.op == "const" and gx.param == Cx and gy.param == Cy and gz.param == 0.0
    H = hessian(f)
    assert all(h.param == 0.0 for row in H for h in row)
    D = np.array([0.5, -2.0, 1.0, 0.25, 1.0])
    g, h = ray_derivatives(f)
    np.testing.assert_array_equal(evaluate(g, {"x": X, "y": X, "dx": D, "dy": D}),
                                  D * (Cx + Cy))
    assert h.param == 0.0
    i = evaluate_interval(f, {"x": Interval(X - 1e-6, X + 1e-6), "y": Interval(X - 1e-6, X + 1e-6)},
                          NUMPY)
    assert np.all(i.lo <= s) and np.all(s <= i.hi)
    assert to_string(f) == "x" + "".join(f" + {v}" if c == 1 else f" + {c!r}*{v}"
                                         for v, c in zip(var, coef))
    _drjit_check(f, np.array([X, X, X]), s, rtol=0, atol=0, per_kernel=1000)


# -- 5. every op, 10,000 deep -----------------------------------------------

# Each step: the expression text (with {} for the inner one), and its value,
# first and second derivative as functions of the inner value v.
STEPS = [
    ("sin({})", np.sin, np.cos, lambda v: -np.sin(v)),
    ("cos({})", np.cos, lambda v: -np.sin(v), lambda v: -np.cos(v)),
    ("({})*0.9 + 0.1", lambda v: v * 0.9 + 0.1, lambda v: 0.9 + 0 * v, lambda v: 0 * v),
    ("abs({} - 0.3)", lambda v: np.abs(v - 0.3), lambda v: np.sign(v - 0.3), lambda v: 0 * v),
    ("sqrt(({})^2 + 1) - 1", lambda v: np.sqrt(v * v + 1) - 1,
     lambda v: v / np.sqrt(v * v + 1), lambda v: (v * v + 1) ** -1.5),
    ("exp(-({})^2)", lambda v: np.exp(-v * v), lambda v: -2 * v * np.exp(-v * v),
     lambda v: (4 * v * v - 2) * np.exp(-v * v)),
    ("log(1 + ({})^2)", lambda v: np.log(1 + v * v), lambda v: 2 * v / (1 + v * v),
     lambda v: (2 - 2 * v * v) / (1 + v * v) ** 2),
    ("1/(1 + ({})^2)", lambda v: 1 / (1 + v * v), lambda v: -2 * v / (1 + v * v) ** 2,
     lambda v: (6 * v * v - 2) / (1 + v * v) ** 3),
    ("(({}) - 0.2)^3", lambda v: (v - 0.2) ** 3, lambda v: 3 * (v - 0.2) ** 2,
     lambda v: 6 * (v - 0.2)),
    ("min({}, 0.5)", lambda v: np.minimum(v, 0.5), lambda v: (v < 0.5) * 1.0, lambda v: 0 * v),
    ("max({}, -0.5)", lambda v: np.maximum(v, -0.5), lambda v: (v > -0.5) * 1.0, lambda v: 0 * v),
    ("-({})", lambda v: -v, lambda v: -1 + 0 * v, lambda v: 0 * v),
    ("({})*y + 0.5*x", None, None, None),   # v*y + x/2: d1 <- y d1 + 1/2, d2 <- y d2
]


def test07_every_op_deep(rng):
    """A chain of DEPTH steps cycling through every public op; oracle: the
    same steps as numpy calls, with value, first and second derivative in x
    carried by forward mode (chain rule) in a plain loop."""
    text = "x"
    for k in range(DEPTH):
        text = STEPS[k % len(STEPS)][0].format(text)
    f = parse(text)
    assert _depth(f) >= DEPTH
    X = rng.uniform(-1, 1, 9)
    Y = rng.uniform(0.5, 1.0, 9)
    v, d1, d2 = X.copy(), np.ones_like(X), np.zeros_like(X)
    creases = np.zeros(X.shape, bool)
    for k in range(DEPTH):
        _, fv, f1, f2 = STEPS[k % len(STEPS)]
        if fv is None:
            v, d1, d2 = v * Y + 0.5 * X, d1 * Y + 0.5, d2 * Y
            continue
        if STEPS[k % len(STEPS)][0].startswith(("abs", "min", "max")):
            kink = {"abs": 0.3, "min": 0.5, "max": -0.5}[STEPS[k % len(STEPS)][0][:3]]
            creases |= np.abs(v - kink) < 1e-9
        v, d1, d2 = fv(v), f1(v) * d1, f2(v) * d1 * d1 + f1(v) * d2
    env = {"x": X, "y": Y, "z": X}
    ok = ~creases
    np.testing.assert_allclose(evaluate(f, env), v, rtol=1e-12, atol=1e-14)
    gx, gy, _ = evaluate(list(gradient(f)), env)
    np.testing.assert_allclose(np.broadcast_to(gx, X.shape)[ok], d1[ok], rtol=1e-9, atol=1e-12)
    hxx = evaluate(hessian(f)[0][0], env)
    np.testing.assert_allclose(np.broadcast_to(hxx, X.shape)[ok], d2[ok], rtol=1e-7, atol=1e-10)
    g, h = evaluate(list(ray_derivatives(f)), {**env, "dx": 1.0 + 0 * X, "dy": 0 * X, "dz": 0 * X})
    np.testing.assert_allclose(np.broadcast_to(g, X.shape)[ok], d1[ok], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(np.broadcast_to(h, X.shape)[ok], d2[ok], rtol=1e-7, atol=1e-10)
    i = evaluate_interval(f, {"x": Interval(X - 1e-9, X + 1e-9), "y": Y, "z": X}, NUMPY)
    assert np.all(i.lo <= v) and np.all(v <= i.hi)
    assert parse(to_string(f)) is f
    _drjit_check(f, np.array([X, Y, X]), v, rtol=1e-3, atol=1e-4, per_kernel=200)


# -- 6. linear time ------------------------------------------------------------

def test08_time_is_linear():
    """Parsing, printing and differentiating a chain 10x longer takes about
    10x the time (a quadratic step would take 100x): CPU time, best of 3,
    ratio below 25."""
    def chain(n):
        return "sin(" * n + "x" + "".join(f" + x*{i}.5)" for i in range(n))

    def cost(n):
        text = chain(n)
        best = math.inf
        for _ in range(3):
            t0 = time.process_time()
            f = parse(text)
            to_string(f)
            gradient.__wrapped__(f)
            best = min(best, time.process_time() - t0)
        return best

    # Without the cycle collector, whose full passes over every object
    # alive (here, all the nodes of the earlier tests) would land in one
    # measurement or the other.
    gc.disable()
    try:
        small, large = cost(1000), cost(10_000)
    finally:
        gc.enable()
    assert large < 25 * small, f"1,000: {small:.3f}s, 10,000: {large:.3f}s"
