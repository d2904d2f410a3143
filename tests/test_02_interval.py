"""Interval soundness by sampling, for every op of the op table and every
library surface: the value, each gradient component and d^T H d.

Oracle: float64 point values at random points inside random boxes (and ray
segments) must lie inside the interval results, computed both in numpy
float64 and in Dr.Jit float32 (where the documented outward padding covers
rounding). No tolerance is added."""
import numpy as np
import pytest
from conftest import ALL_CASES, case_expr, case_id, random_boxes

from drjit.llvm import Float

from lgshape import bounds
from lgshape.arraymath import NUMPY, DrJitMath
from lgshape.expr import evaluate, evaluate_interval, gradient, ray_derivatives
from lgshape.interval import Interval

BOXES, SAMPLES = 400, 24


def _targets(f):
    g = gradient(f)
    return [("f", f), ("df/dx", g[0]), ("df/dy", g[1]), ("df/dz", g[2])]


def _assert_inside(name, lo, hi, values):
    lo, hi = np.broadcast_to(lo, values.shape), np.broadcast_to(hi, values.shape)
    ok = np.isnan(values) | ((lo <= values) & (values <= hi))
    bad = np.argwhere(~ok)
    assert bad.size == 0, (f"{name}: {len(bad)} samples outside; first: value "
                           f"{values[tuple(bad[0])]} not in [{lo[tuple(bad[0])]}, {hi[tuple(bad[0])]}]")


@pytest.mark.parametrize("backend", ["numpy64", "drjit32"])
@pytest.mark.parametrize("case", ALL_CASES, ids=case_id)
def test01_box_soundness(case, backend, rng):
    f, bbox = case_expr(*case)
    lo, hi = random_boxes(rng, bbox, BOXES)
    pts = lo[:, None, :] + (hi - lo)[:, None, :] * rng.uniform(0, 1, (BOXES, SAMPLES, 3))
    pts[:, 0], pts[:, 1] = lo, hi                      # include corners
    targets = _targets(f)
    values = evaluate([e for _, e in targets], {v: pts[..., i] for i, v in enumerate("xyz")})
    if backend == "numpy64":
        res = evaluate_interval([e for _, e in targets], bounds.box_env(lo, hi), NUMPY)
        ivs = [(np.broadcast_to(r.lo, (BOXES,)), np.broadcast_to(r.hi, (BOXES,))) for r in res]
    else:
        m = DrJitMath(Float)
        env = {v: Interval(Float(lo[:, i]), Float(hi[:, i])) for i, v in enumerate("xyz")}
        res = evaluate_interval([e for _, e in targets], env, m)
        ivs = [(np.broadcast_to(np.asarray(r.lo + 0 * env["x"].lo, np.float64), (BOXES,)),
                np.broadcast_to(np.asarray(r.hi + 0 * env["x"].lo, np.float64), (BOXES,))) for r in res]
    for (name, _), (ilo, ihi), v in zip(targets, ivs, values):
        v = np.broadcast_to(v, (BOXES, SAMPLES))
        _assert_inside(name, ilo[:, None], ihi[:, None], v)


@pytest.mark.parametrize("case", ALL_CASES, ids=case_id)
def test02_segment_soundness_dhd(case, rng):
    """g = dF/dt and h = d^T H d over ray segments, in Dr.Jit float32."""
    f, bbox = case_expr(*case)
    n = 2000
    lo, hi = np.asarray(bbox[0]), np.asarray(bbox[1])
    o = lo + (hi - lo) * rng.uniform(0, 1, (n, 3))
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    a = rng.uniform(-0.5, 0.5, n)
    b = a + np.linalg.norm(hi - lo) * rng.uniform(1e-4, 0.3, n) ** 2
    g, h = ray_derivatives(f)
    m = DrJitMath(Float)
    O = [Float(o[:, i]) for i in range(3)]
    D = [Float(d[:, i]) for i in range(3)]
    t = a[:, None] + (b - a)[:, None] * rng.uniform(0, 1, (n, SAMPLES))
    t[:, 0], t[:, 1] = a, b
    env = {v: o[:, None, i] + t * d[:, None, i] for i, v in enumerate("xyz")}
    env.update({"d" + v: d[:, None, i] for i, v in enumerate("xyz")})
    for name, e in (("g", g), ("h", h)):
        r = bounds.segment_interval(e, O, D, Float(a), Float(b), m)
        ilo = np.broadcast_to(np.asarray(r.lo + 0 * O[0], np.float64), (n,))
        ihi = np.broadcast_to(np.asarray(r.hi + 0 * O[0], np.float64), (n,))
        v = np.broadcast_to(evaluate(e, env), (n, SAMPLES))
        _assert_inside(name, ilo[:, None], ihi[:, None], v)


def test03_domain_edges():
    """Division by an interval containing 0 gives infinite bounds; sqrt and
    log enclose their defined part and give the empty marker [+inf, +inf]
    where nothing is defined; NaN never narrows a bound; overflow keeps its
    sign. Oracle: the closed-form ranges."""
    from lgshape import interval as iv
    m = NUMPY
    A = lambda lo, hi: Interval(np.array([lo]), np.array([hi]))  # noqa: E731
    r = iv.i_div(m, A(1.0, 2.0), A(-1.0, 1.0))
    assert r.lo[0] == -np.inf and r.hi[0] == np.inf
    r = iv.i_sqrt(m, A(-1.0, 4.0))
    assert (r.lo[0], r.hi[0]) == (0.0, 2.0)
    r = iv.i_log(m, A(-1.0, 4.0))
    assert r.lo[0] == -np.inf and r.hi[0] == np.log(4.0)
    for op in (iv.i_sqrt, iv.i_log):
        r = op(m, A(-2.0, -1.0))
        assert iv.is_empty(m, r)[0] and iv.is_empty(m, iv.pad(m, r))[0]
    nan = iv.pad(m, A(np.nan, np.nan))
    assert nan.lo[0] == -np.inf and nan.hi[0] == np.inf
    inf_minus_inf = iv.pad(m, iv.i_sub(m, A(np.inf, np.inf), A(np.inf, np.inf)))
    assert inf_minus_inf.lo[0] == -np.inf and inf_minus_inf.hi[0] == np.inf
    over = iv.pad(m, A(np.inf, np.inf))        # a positive overflow stays positive
    assert over.lo[0] > 0


@pytest.mark.parametrize("backend", ["numpy64", "drjit32"])
def test04_small_values_keep_their_sign(backend):
    """exp of a very negative argument stays positive after padding, so its
    log is finite and narrow (the float32 padding once added an absolute
    1e-37 and made log(exp(-85)) infinite; the absolute slack left is the
    smallest normal float, 1.2e-38). Oracle: log(exp(a)) = a."""
    from lgshape.expr import node as N
    m = NUMPY if backend == "numpy64" else DrJitMath(Float)
    arr = np.asarray if backend == "numpy64" else Float
    a = -80.0
    e = N.log(N.exp(N.var("x") + a))
    r = evaluate_interval(e, {"x": Interval(arr([0.0]), arr([1e-3]))}, m)
    lo, hi = float(np.asarray(r.lo)[0]), float(np.asarray(r.hi)[0])
    assert lo <= a and a + 1e-3 <= hi
    assert np.isfinite(lo) and hi - lo < 1e-2
