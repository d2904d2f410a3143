"""The JIT backend's arithmetic against the error model that the bounds
assume (:mod:`lgshape.arraymath`): sin, cos, exp and log within ``eps_t``
as the point-error rules use it, division and square root correctly
rounded where the search is traced (:func:`lgshape.arraymath.exact_arithmetic`).

The suite's backend is LLVM unless LGSHAPE_TEST_VARIANT names a CUDA
variant; on CUDA these are the checks that fail with Dr.Jit's defaults
(float32 transcendentals on the multi-function unit, approximate division
and square root in fast-math mode). Oracles: numpy's float64 functions
(within an ulp of float64, far below the float32 margins; for float64 the
64-ulp margin leaves 63) and numpy's float32 division and square root
(IEEE: correctly rounded)."""
import math

import numpy as np
import pytest
from conftest import JIT

import drjit as dr
from lgshape.arraymath import DrJitMath, exact_arithmetic
from lgshape.expr.raytrig import EPS_T32, U32

N = 20000


def _args(rng, lo, hi):
    return rng.uniform(lo, hi, N)


def _near_zeros(rng, k_max):
    """Points within 1e-6 (relative) of k pi / 2, where sin or cos is near
    0 (an absolute library error is largest relative to the value there)."""
    k = rng.integers(-k_max, k_max, N)
    return k * (0.5 * math.pi) * (1.0 + rng.uniform(-1e-6, 1e-6, N))


@pytest.fixture(params=[32, 64], ids=["float32", "float64"])
def math_(request):
    Float = JIT.Float if request.param == 32 else JIT.Float64
    return DrJitMath(Float), np.float32 if request.param == 32 else np.float64


def _run(m, fn, x):
    return np.asarray(fn(m.Float(x)), np.float64)


def test01_sin_cos_within_the_periodic_rule(math_, rng):
    """e_periodic with an exact argument: |sin x - computed| <= eps_t + 2 u |x|."""
    m, t = math_
    x = np.concatenate([_args(rng, -300, 300), _near_zeros(rng, 200), _args(rng, -4, 4)])
    x = x.astype(t).astype(np.float64)
    for fn, ref in ((m.sin, np.sin), (m.cos, np.cos)):
        err = np.abs(_run(m, fn, x) - ref(x))
        assert np.all(err <= m.eps_t + 2.0 * m.u * np.abs(x)), (fn, np.max(err))
    s, c = m.sincos(m.Float(x))
    for v, ref in ((s, np.sin), (c, np.cos)):
        assert np.all(np.abs(np.asarray(v, np.float64) - ref(x))
                      <= m.eps_t + 2.0 * m.u * np.abs(x))


def test02_exp_log_within_their_rules(math_, rng):
    """e_exp with an exact argument: |exp x - v| <= eps_t v + tiny (v the
    computed value); e_log: |log x - v| <= eps_t |v| + 4 u."""
    m, t = math_
    top = 88.0 if t is np.float32 else 700.0
    x = np.concatenate([_args(rng, -top, top), _args(rng, -2, 2)]).astype(t).astype(np.float64)
    v = _run(m, m.exp, x)
    assert np.all(np.abs(v - np.exp(x)) <= m.eps_t * v + m.tiny)
    lo_exp = -120 if t is np.float32 else -1000
    y = np.concatenate([2.0 ** _args(rng, lo_exp, -lo_exp), 1.0 + _args(rng, -1e-3, 1e-3)])
    y = y.astype(t).astype(np.float64)
    v = _run(m, m.log, y)
    assert np.all(np.abs(v - np.log(y)) <= m.eps_t * np.abs(v) + 4.0 * m.u)


def test03_float32_sincos_of_the_ray_sinusoids(rng):
    """raytrig's model of ``sincos32``: EPS_T32 + 2 U32 |x| (an ulp of |x|
    each for the argument's rounding and its reduction; x is float32
    already, so the margin is twice what the reduction needs)."""
    m = DrJitMath(JIT.Float64)
    x = np.concatenate([_args(rng, -300, 300), _near_zeros(rng, 200)])
    x = x.astype(np.float32).astype(np.float64)
    s, c = m.sincos32(JIT.Float64(x))
    for v, ref in ((s, np.sin), (c, np.cos)):
        assert np.all(np.abs(np.asarray(v, np.float64) - ref(x)) <= EPS_T32 + 2 * U32 * np.abs(x))


def test04_division_and_sqrt_correctly_rounded_where_the_search_is_traced(rng):
    """Inside exact_arithmetic, float32 a / b and sqrt(a) equal numpy's
    (IEEE) bit for bit, over normal operands and results, divisors above
    2^126 included (CUDA's div.approx gives 0 there)."""
    a = (rng.uniform(1, 2, N) * 2.0 ** rng.integers(-60, 60, N)).astype(np.float32)
    b = (rng.uniform(1, 2, N) * 2.0 ** rng.integers(-60, 60, N)).astype(np.float32)
    a[:100] = np.float32(3e38)
    b[:100] = np.float32(1e38)
    Float = JIT.Float
    A, B = Float(a), Float(b)
    with dr.scoped_set_flag(dr.JitFlag.FastMath, True), exact_arithmetic(Float):
        q, r = A / B, dr.sqrt(A)          # (Dr.Jit's default; conftest clears it on CUDA)
    dr.eval(q, r)
    assert np.array_equal(np.asarray(q), a / b)
    assert np.array_equal(np.asarray(r), np.sqrt(a))
