"""Float64 reference intersections, independent of the Dr.Jit kernel.

Two oracles over numpy float64, for tests and the benchmark:

- :func:`polynomial_roots`: for an algebraic f of known degree n, F(t) along
  each ray is expanded exactly (sampled at n + 1 Chebyshev nodes of the
  clipped segment and solved for its coefficients), and all n roots come
  from the eigenvalues of the companion matrix (batched ``numpy.linalg``);
- :func:`first_sign_change`: for any f, dense sampling of F along the ray
  and bisection of the first sign change (a brute-force reference; it can
  miss features thinner than its step, which is why the step is given).

``F`` is a callable ``F(X, Y, Z) -> values`` on float64 arrays.
"""
from __future__ import annotations

import numpy as np

from .expr import evaluate, gradient


def clip_to_box(o, d, lo, hi, t_min=0.0, t_max=np.inf):
    """Per-ray [t0, t1] of o + t d inside the box (t0 > t1 where missed)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        ta, tb = (lo - o) * inv, (hi - o) * inv
        tn = np.where(d == 0, np.where((o >= lo) & (o <= hi), -np.inf, np.inf), np.minimum(ta, tb))
        tf = np.where(d == 0, np.where((o >= lo) & (o <= hi), np.inf, -np.inf), np.maximum(ta, tb))
    return np.maximum(tn.max(1), t_min), np.minimum(tf.min(1), t_max)


def along(F, o, d, t):
    """F at o + t d; t has shape (n,) or (n, k)."""
    t = np.asarray(t, np.float64)
    if t.ndim == 1:
        return F(*(o[:, i] + t * d[:, i] for i in range(3)))
    return F(*(o[:, None, i] + t * d[:, None, i] for i in range(3)))


def polynomial_roots(F, degree: int, o, d, t0, t1):
    """All complex roots t of F along each ray, shape (n, degree); the
    expansion is made over [t0, t1] (rays with t0 > t1 give NaN)."""
    n = len(o)
    ok = t1 > t0
    tc, th = 0.5 * (t0 + t1), 0.5 * (t1 - t0)
    th = np.where(ok, th, 1.0)
    tc = np.where(ok, tc, 0.0)
    nodes = np.cos(np.pi * (np.arange(degree + 1) + 0.5) / (degree + 1))
    V = np.vander(nodes, degree + 1, increasing=True)        # s^k
    samples = along(F, o, d, tc[:, None] + th[:, None] * nodes[None])
    coef = np.linalg.solve(V, samples.T).T                   # (n, degree + 1), s^0 first
    lead = coef[:, -1]
    scale = np.abs(coef).max(1)
    lead = np.where(np.abs(lead) < 1e-14 * scale, 1e-14 * scale + 1e-300, lead)
    comp = np.zeros((n, degree, degree))
    comp[:, 1:, :-1] = np.eye(degree - 1)
    comp[:, :, -1] = -coef[:, :-1] / lead[:, None]
    s = np.linalg.eigvals(comp)
    t = tc[:, None] + th[:, None] * s
    t[~ok] = np.nan
    return t


def first_sign_change(F, o, d, t0, t1, steps: int = 4096, bisections: int = 50):
    """First root of F on [t0, t1] by sampling ``steps`` points and bisecting
    the first sign change; inf where there is none."""
    n = len(o)
    ok = t1 > t0
    s = np.linspace(0.0, 1.0, steps + 1)
    t = t0[:, None] + (t1 - t0)[:, None] * s[None]
    v = along(F, o, d, t)
    change = (np.sign(v[:, :-1]) * np.sign(v[:, 1:]) <= 0) & ok[:, None]
    has = change.any(1)
    k = np.argmax(change, 1)
    a, b = t[np.arange(n), k], t[np.arange(n), k + 1]
    fa = v[np.arange(n), k]
    a, b = bisect_sign_change(F, o, d, a, b, fa, bisections)
    return np.where(has, 0.5 * (a + b), np.inf)


def bisect_sign_change(F, o, d, a, b, fa, bisections: int = 50):
    """The brackets [a, b] of sign changes of F along the rays o + t d (one
    per row; fa = F(a)) halved ``bisections`` times: (a, b)."""
    for _ in range(bisections):
        mid = 0.5 * (a + b)
        fm = along(F, o, d, mid)
        left = np.sign(fm) * np.sign(fa) <= 0
        b = np.where(left, mid, b)
        a, fa = np.where(left, a, mid), np.where(left, fa, fm)
    return a, b


def rod_intervals(o, d, a, b, r):
    """Entry and exit t (n, m) of the rays o + t d (n, 3) through the solid
    cylinders of radius r_j (m,) about the segments a_j b_j (m, 3), capped
    flat, NaN where the line misses one."""
    ba = b - a
    L = np.linalg.norm(ba, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.where(L[:, None] > 0, ba / np.where(L > 0, L, 1.0)[:, None], np.array([0.0, 0.0, 1.0]))
    oa = o[:, None, :] - a[None]
    ou = (oa * u[None]).sum(-1)
    du = d @ u.T
    op = oa - ou[..., None] * u[None]
    dp = d[:, None, :] - du[..., None] * u[None]
    A = (dp * dp).sum(-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        tc = np.where(A > 0, -(op * dp).sum(-1) / A, 0.0)
        m = op + tc[..., None] * dp
        rho = np.sqrt((m * m).sum(-1))
        q = (r[None] - rho) * (r[None] + rho)
        h = np.where(A > 0, np.sqrt(np.maximum(q, 0) / A), np.inf)
        c0, c1 = tc - h, tc + h
        s0, s1 = -ou / du, (L[None] - ou) / du
        par = du == 0
        inside = (ou >= 0) & (ou <= L[None])
        a0 = np.where(par, np.where(inside, -np.inf, np.inf), np.minimum(s0, s1))
        a1 = np.where(par, np.where(inside, np.inf, -np.inf), np.maximum(s0, s1))
    tn, tf = np.maximum(c0, a0), np.minimum(c1, a1)
    ok = (q >= 0) & (tn <= tf)
    return np.where(ok, tn, np.nan), np.where(ok, tf, np.nan)


#: A complex root counts as real when |Im t| is below this (in diagonals).
REAL_ROOT = 1e-6


def numpy_f(expr):
    """f as a float64 numpy callable F(X, Y, Z) (the reference's view of f)."""
    return lambda X, Y, Z: evaluate(expr, {"x": X, "y": Y, "z": Z})


def nearest_root(spec, o, d, t_min=0.0, degree=None, steps=4096, t_max=None):
    """Float64 nearest root of f along each float32 ray o + t d in the box,
    beyond ``t_min`` (and before ``t_max`` where given): exact polynomial
    roots when ``degree`` is given, else the first sign change of a
    ``steps``-point scan refined by bisection. Returns t (inf where none)."""
    o, d = np.asarray(o, np.float64), np.asarray(d, np.float64)
    lo, hi = (np.asarray(v, np.float64) for v in spec.bbox)
    t0, t1 = clip_to_box(o, d, lo, hi, t_min=t_min)
    if t_max is not None:
        t1 = np.minimum(t1, t_max)
    F = numpy_f(spec.expr)
    out = np.full(len(o), np.inf)
    ok = np.flatnonzero(t1 > t0)
    if degree is not None:
        diag = float(np.linalg.norm(hi - lo))
        for k in range(0, len(ok), 8192):
            i = ok[k:k + 8192]
            r = polynomial_roots(F, degree, o[i], d[i], t0[i], t1[i])
            real = np.abs(r.imag) <= REAL_ROOT * diag
            t = np.where(real & (r.real >= t0[i, None]) & (r.real <= t1[i, None]), r.real, np.inf)
            out[i] = t.min(1)
        return out
    chunk = max(1, 2**19 // steps)          # ~0.5 M samples at a time
    for k in range(0, len(ok), chunk):
        i = ok[k:k + chunk]
        out[i] = first_sign_change(F, o[i], d[i], t0[i], t1[i], steps=steps)
    return out


def reference_normal(spec, p):
    """Unit float64 gradient of f at points p (n, 3); NaN where grad f = 0."""
    g = evaluate(list(gradient(spec.expr)), dict(zip("xyz", np.asarray(p, np.float64).T)))
    g = np.stack([np.broadcast_to(v, len(p)) for v in g], 1).astype(np.float64)
    n = np.linalg.norm(g, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, g / n, np.nan)
