"""A polynomial f along a ray, as a polynomial in the ray parameter.

For f a polynomial in x, y, z of degree n, F(s) = f(e + s d) is a
polynomial of degree <= n in s. Its coefficients are computed once per ray
(:func:`ray_polynomial`, a walk of the expression with polynomial
arithmetic), each with a bound of its rounding error. Every later question
about F on the ray is then a question about n + 1 numbers:

- :func:`shift`: the coefficients about any point t (a Taylor shift, n(n+1)/2
  multiply-adds), with a bound of their errors: F(t) and F'(t) are the
  first two;
- :func:`forms`: from them, F's and F''s quadratic forms over |s - t| <= r
  (:class:`~lgshape.expr.quadratic.Quad`), whose remainders are the
  higher coefficients' terms: the enclosures the search's test takes,
  without evaluating the expression again.

Errors: the ray e + s d is exact as given (the search's float64 ray); a
coefficient's bound covers every rounding of the walk (running error
analysis, as :mod:`lgshape.pointerror`, with the magnitudes actually met).
Constant subexpressions that are not polynomial ops (sqrt(2), ...) are
point values with their own error bounds. Anything NaN or infinite makes
the bounds infinite or NaN: no information, never a wrong one.
"""
from __future__ import annotations

import math

from ..arraymath import powi
from .evaluate import evaluate_with_error
from .node import Expr, topological

#: The largest degree the search takes this way (the coefficients are live
#: state of the search loop: 2 (n + 1) float64 values a ray).
MAX_DEGREE = 8

_POLY_OPS = ("add", "sub", "mul", "neg", "pow", "div")


def ray_degree(f: Expr) -> float:
    """f's degree where :func:`ray_polynomial` takes it, else inf."""
    n = f.degree()
    return n if n <= MAX_DEGREE else math.inf


def ray_polynomial(f: Expr, e, d, m):
    """([c_0 .. c_n], [w_0 .. w_n]): F(s) = f(e + s d) = sum c_k s^k up to
    |c_k - exact c_k| <= w_k (arrays of ``m``, float64; e, d: three arrays,
    exact). f must have a finite degree <= MAX_DEGREE."""
    deg = f.degree()
    if not deg <= MAX_DEGREE:
        raise ValueError(f"not a polynomial of degree <= {MAX_DEGREE} (degree {deg})")
    u = m.u
    val = {}
    for n in topological([f]):
        if n.op == "var" and n.param in ("x", "y", "z"):
            a = "xyz".index(n.param)
            val[id(n)] = ([e[a], d[a]], [0.0, 0.0])
        elif n.op != "var" and all(len(val[id(x)][0]) == 1 for x in n.args) \
                and (n.args or n.op in ("const", "named")):
            # a constant (or a constant subexpression): its point value
            v, ev = evaluate_with_error(n, {}, {}, m)
            val[id(n)] = ([v], [ev])
        elif n.op in ("add", "sub"):
            (a, ea), (b, eb) = (val[id(x)] for x in n.args)
            k = 1.0 if n.op == "add" else -1.0
            c, w = [], []
            for i in range(max(len(a), len(b))):
                ai, bi = (a[i] if i < len(a) else None), (b[i] if i < len(b) else None)
                if bi is None:
                    c.append(ai), w.append(ea[i])
                elif ai is None:
                    c.append(k * bi), w.append(eb[i])
                else:
                    v = ai + k * bi
                    c.append(v), w.append(ea[i] + eb[i] + u * m.abs(v))
            val[id(n)] = (c, w)
        elif n.op == "neg":
            a, ea = val[id(n.args[0])]
            val[id(n)] = ([-v for v in a], list(ea))
        elif n.op == "mul":
            val[id(n)] = _mul(m, val[id(n.args[0])], val[id(n.args[1])])
        elif n.op == "pow":
            val[id(n)] = _pow(m, val[id(n.args[0])], int(n.param))
        elif n.op == "div":              # by a constant (degree 0)
            (a, ea), (b, eb) = (val[id(x)] for x in n.args)
            b, eb = b[0], eb[0]
            room = m.abs(b) - eb
            c, w = [], []
            for ai, ei in zip(a, ea):
                v = ai / b
                err = (ei + m.abs(v) * (1.0 + 2.0 * u) * eb) / room + u * m.abs(v)
                c.append(v), w.append(m.select(room > 0, err, math.inf))
            val[id(n)] = (c, w)
        else:
            raise ValueError(f"op {n.op!r} in a polynomial")
    c, w = val[id(f)]
    return list(c), [v * (1.0 + 2.0**-40) for v in w]


def _mul(m, A, B):
    """Product of two coefficient lists with error bounds: each c_k a sum
    of at most p products (p + 1 roundings, within (p + 1) u of the sum of
    their magnitudes), plus the arguments' errors times magnitudes."""
    (a, ea), (b, eb) = A, B
    u = m.u
    c, w = [], []
    for k in range(len(a) + len(b) - 1):
        terms = [(i, k - i) for i in range(len(a)) if 0 <= k - i < len(b)]
        s, mag, err = None, None, None
        for i, j in terms:
            p = a[i] * b[j]
            s = p if s is None else s + p
            mp = m.abs(p)
            mag = mp if mag is None else mag + mp
            t = m.abs(a[i]) * eb[j] + m.abs(b[j]) * ea[i] + ea[i] * eb[j]
            err = t if err is None else err + t
        c.append(s)
        w.append(err + (len(terms) + 1) * u * mag)
    return c, w


def _pow(m, A, n: int):
    if n == 0:
        z = 0.0 * A[0][0]
        return [z + 1.0], [z]
    return powi(A, n, lambda p, q: _mul(m, p, q))


def shift(m, c, w, t):
    """The coefficients about t: F(t + s) = sum c'_k s^k (the Taylor shift
    by repeated synthetic division, n(n+1)/2 multiply-adds), and the bound
    of their errors as a polynomial: (c', W) with

        sum_k |c'_k - exact c'_k| x^k  <=  W(|t| + x)  for every x >= 0,

    W(y) = sum_k (4 (n + 1) u |c_k| + w_k) y^k: each c'_k comes from at most
    n steps (two roundings each) over terms whose magnitudes, summed, are the
    same shift of |c_k| by |t|, and the shift of any polynomial of positive
    coefficients by |t|, at x, is its value at |t| + x. So F(t) = c'_0 within
    W(|t|), and the errors of a form over |s| <= r are within W(|t| + r)."""
    n = len(c) - 1
    cs = list(c)
    for i in range(n):
        for k in range(n - 1, i - 1, -1):
            cs[k] = t * cs[k + 1] + cs[k]
    return cs, _shift_bound(m, c, w)


def _shift_bound(m, c, w):
    """:func:`shift`'s W (the same for any t)."""
    g = 4.0 * len(c) * m.u
    return [g * m.abs(ci) + wi for ci, wi in zip(c, w)]


def value_and_slope(c, t):
    """F(t) and F'(t) from the coefficients (Horner, no error bounds: for
    Newton's steps)."""
    F, g = c[-1], 0.0 * t
    for ck in c[-2::-1]:
        g = g * t + F
        F = F * t + ck
    return F, g


def bound(m, W, y, derivative=False):
    """W(y) (or W'(y)) for y >= 0, rounded up: positive terms, Horner's
    roundings within 2 n u of the sum."""
    n = len(W) - 1
    up = 1.0 + 4.0 * (n + 1) * m.u
    if derivative:
        W = [k * W[k] for k in range(1, n + 1)]
        if not W:
            return 0.0 * y
    v = W[-1]
    for k in range(len(W) - 2, -1, -1):
        v = v * y + W[k]
    return v * up


def forms(seg, cs, W, at):
    """F's and F''s quadratic forms over |s| <= seg.r about the shift point
    t (``at`` = |t|), from the shifted coefficients and their error bound
    (:func:`shift`): (Qf, Qg). ``seg``: a
    :class:`~lgshape.expr.quadratic.Segment` of the same precision."""
    from .quadratic import Quad
    m, r = seg.m, seg.r
    n = len(cs) - 1
    u = m.u
    up = 1.0 + 4.0 * (n + 2) * u
    z = 0.0 * cs[0]
    coef = list(cs) + [z] * max(0, 4 - n)
    y = at + r
    # F: c'_0 + c'_1 s + c'_2 s^2; the higher terms and the errors in R
    Rf = bound(m, W, y)
    rk = 1.0 + z
    for k in range(1, n + 1):
        rk = rk * r * up
        if k >= 3:
            Rf = Rf + m.abs(cs[k]) * rk
    Qf = Quad(coef[0], coef[1], coef[2], Rf * up)
    # F' = sum k c'_k s^(k-1): c'_1 + 2 c'_2 s + 3 c'_3 s^2 (3 c'_3 rounded)
    c3 = 3.0 * coef[3]
    Rg = bound(m, W, y, derivative=True) + u * m.abs(c3) * seg.r2
    rk = 1.0 + z
    for k in range(2, n + 1):
        rk = rk * r * up
        if k >= 4:
            Rg = Rg + k * m.abs(cs[k]) * rk
    Qg = Quad(coef[1], 2.0 * coef[2], c3, Rg * up)
    return Qf, Qg


def _bernstein_weights(n: int):
    """lam[j][k] = C(j, k) / C(n, k) for k <= j: the Bernstein coefficients
    over [0, 1] of a polynomial sum_k d_k u^k are b_j = sum_k lam[j][k] d_k."""
    return [[math.comb(j, k) / math.comb(n, k) for k in range(j + 1)] for j in range(n + 1)]


def clip_first_root(m, c, w, span, steps: int = 1):
    """Where the first root of F on [0, span] can be, from the convex hull
    of F's Bernstein coefficients (Bezier clipping from both ends, ``steps``
    times): (free, first), float64. ``free``: F has no root in [0, span];
    else none in [0, first).

    One step, on [a, a + h]: the coefficients about a (:func:`shift`),
    scaled to u in [0, 1] (d_k = c'_k h^k), and their Bernstein
    coefficients b_j. Every error is in one bound E: the shift's W(a + h),
    and the roundings of the scaling and of the sums (each b_j within
    (2n + 6) u sum |d_k| of its exact value). Where b_0 is beyond E, with s
    its sign, beta_j = s b_j - E are the control points of a polynomial
    below s F(a + u h). They lie above the line beta_0 + sigma u, sigma =
    min_j (beta_j - beta_0) n / j (a supporting line at the first point;
    sum_j (j / n) B_j(u) = u), so s F > 0 for u < beta_0 / -sigma, and
    everywhere on [0, 1] where sigma >= 0. The same from the right end
    (b_n beyond E) shortens h; where the two clips meet, no root. NaN or
    infinite coefficients clip nothing."""
    n = len(c) - 1
    u = m.u
    lam = _bernstein_weights(n)
    zero = 0.0 * span
    a, h = zero, span * (1.0 + 4.0 * u)
    free = zero != zero                                  # all False
    for step in range(steps):
        # (about a = 0 at first: the coefficients as they are)
        cs, W = (c, _shift_bound(m, c, w)) if step == 0 else shift(m, c, w, a)
        d, hk = [], 1.0 + zero
        for k in range(n + 1):
            d.append(cs[k] * hk)
            hk = hk * h
        M = zero
        for v in d:
            M = M + m.abs(v)
        E = bound(m, W, a + h) + (4.0 * n + 16.0) * u * M
        b = []
        for j in range(n + 1):
            s = d[0] * lam[j][0]
            for k in range(1, j + 1):
                s = s + d[k] * lam[j][k]
            b.append(s)
        finite = m.isfinite(E)
        tl = _clip_from(m, b, E, n)
        tr = _clip_from(m, b[::-1], E, n)
        tl = m.select(finite, tl, 0.0)
        tr = m.select(finite, tr, 0.0)
        # the quotients with 2^-40 relative to spare for their roundings
        tl, tr = tl * (1.0 - 2.0**-40), tr * (1.0 - 2.0**-40)
        clear = tl + tr > 1.0
        free = free | clear
        a_next = a + tl * h
        a_next = a_next - (m.abs(a_next) * 2.0**-50 + 2.0**-1020)      # rounded down
        end = a + h * (1.0 - tr)
        end = end + (m.abs(end) * 2.0**-50 + 2.0**-1020)               # rounded up
        keep = ~free
        a = m.select(keep, m.maximum(a_next, a), a)
        h = m.select(keep, m.minimum((end - a) * (1.0 + 4.0 * u), h), h)
    return free, m.select(free, span, a)


def _clip_from(m, b, E, n):
    """How far from b's first end, as a fraction of the interval, s F keeps
    its sign (0 where b_0 is within E of 0; >= 1: everywhere)."""
    pos = b[0] > E
    sg = m.select(pos, 1.0, -1.0)
    beta0 = sg * b[0] - E
    slope = None
    for j in range(1, n + 1):
        # (beta_j - beta_0) n / j, lowered by its roundings (the two
        # differences may cancel: their errors are relative to the terms)
        v = (sg * b[j] - E - beta0) * (n / j) \
            - (4.0 * n / j) * m.u * (m.abs(b[j]) + E + beta0)
        slope = v if slope is None else m.minimum(slope, v)
    theta = m.select(slope >= 0, 2.0, beta0 / m.maximum(-slope, 1e-300))
    return m.select((beta0 > 0) & (theta == theta), m.minimum(theta, 2.0), 0.0)
