"""Exact derivatives against central finite differences in float64 numpy.

Oracle: fourth-order central differences (five-point stencils) for the
gradient and, along a ray F(t) = f(p + t d), for g = F' and d^T H d = F'', at
random points
of the box, for every op of the op table and every library surface. Points
within 1e-3 of a crease of abs/min/max (where the derivative jumps) are left
out. Tolerance: relative 1e-5 (first derivatives) and 1e-4 (second) of the
derivative's scale; the step is 1e-4, so the stencils' truncation error is
below 1e-8 even for the spikes' 0.01-wide features."""
import numpy as np
import pytest
from conftest import ALL_CASES, case_expr, case_id

from lgshape.expr import evaluate, gradient, ray_derivatives
from lgshape.expr.node import topological

N = 3000


def _away_from_creases(f, P):
    """Mask of points not within 1e-3 of a crease of abs/min/max/step."""
    ok = np.ones(P.shape[0], bool)
    env = {v: P[:, i] for i, v in enumerate("xyz")}
    for n in topological([f]):
        if n.op in ("abs", "step", "kink", "min", "max"):
            if n.op in ("min", "max"):
                a, b = evaluate(list(n.args), env)
                ok &= np.abs(np.broadcast_to(a - b, ok.shape)) > 1e-3
            else:
                ok &= np.abs(np.broadcast_to(evaluate(n.args[0], env), ok.shape)) > 1e-3
    return ok


def _points(rng, bbox):
    lo, hi = np.asarray(bbox[0]), np.asarray(bbox[1])
    return lo + (hi - lo) * rng.uniform(0.02, 0.98, (N, 3))


@pytest.mark.parametrize("case", ALL_CASES, ids=case_id)
def test01_gradient(case, rng):
    f, bbox = case_expr(*case)
    P = _points(rng, bbox)
    P = P[_away_from_creases(f, P)]
    env = {v: P[:, i] for i, v in enumerate("xyz")}
    exact = [np.broadcast_to(g, len(P)) for g in evaluate(list(gradient(f)), env)]
    eps = 1e-4
    for i, v in enumerate("xyz"):
        def at(s):
            e = dict(env)
            e[v] = P[:, i] + s * eps
            return evaluate(f, e)
        fd = (at(-2) - 8 * at(-1) + 8 * at(1) - at(2)) / (12 * eps)
        scale = 1 + np.abs(fd)
        err = np.abs(exact[i] - fd) / scale
        assert np.nanmax(err) < 1e-5, f"d/d{v}: max rel. error {np.nanmax(err):.2e}"


@pytest.mark.parametrize("case", ALL_CASES, ids=case_id)
def test02_ray_second_derivative(case, rng):
    f, bbox = case_expr(*case)
    P = _points(rng, bbox)
    D = rng.normal(size=P.shape)
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    eps = 1e-4
    ok = _away_from_creases(f, P) & _away_from_creases(f, P + 2 * eps * D) & \
        _away_from_creases(f, P - 2 * eps * D)
    P, D = P[ok], D[ok]
    g, h = ray_derivatives(f)
    env = {v: P[:, i] for i, v in enumerate("xyz")}
    env.update({"d" + v: D[:, i] for i, v in enumerate("xyz")})
    g_exact, h_exact = (np.broadcast_to(a, len(P)) for a in evaluate([g, h], env))

    def F(s):
        return evaluate(f, {v: P[:, i] + s * D[:, i] for i, v in enumerate("xyz")})

    f0, fp, fm, fp2, fm2 = F(0.0), F(eps), F(-eps), F(2 * eps), F(-2 * eps)
    g_fd = (fm2 - 8 * fm + 8 * fp - fp2) / (12 * eps)
    h_fd = (-fp2 + 16 * fp - 30 * f0 + 16 * fm - fm2) / (12 * eps**2)
    err_g = np.abs(g_exact - g_fd) / (1 + np.abs(g_fd))
    # The stencil itself loses 64 |F| ulp / (12 eps^2) to rounding.
    rounding = 64 * 2.3e-16 * np.maximum(np.abs(fp2), np.abs(fm2)) / (12 * eps**2)
    err_h = np.maximum(np.abs(h_exact - h_fd) - rounding, 0) / (1 + np.abs(h_fd))
    assert np.nanmax(err_g) < 1e-5, f"g: max rel. error {np.nanmax(err_g):.2e}"
    assert np.nanmax(err_h) < 1e-4, f"h: max rel. error {np.nanmax(err_h):.2e}"
