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

from ..arraymath import powi, zero_like
from .evaluate import evaluate_with_error
from .node import Expr, topological
from .quadratic import Quad

#: The largest degree the search takes this way (the coefficients are live
#: state of the search loop: 2 (n + 1) float64 values a ray).
MAX_DEGREE = 8

_POLY_OPS = ("add", "sub", "mul", "neg", "pow", "div")


def ray_degree(f: Expr) -> float:
    """f's degree where :func:`ray_polynomial` takes it, else inf."""
    n = f.degree()
    return n if n <= MAX_DEGREE else math.inf


#: The coefficients' error bounds a priori (:func:`_ray_polynomial_apriori`:
#: the same expansion on magnitudes, times the roundings on the longest
#: path) rather than by running error analysis (each op's bound from its
#: arguments' values and bounds, about three times the arithmetic of the
#: coefficients). The bounds are 1-5x the running ones (median over random
#: rays; up to 100x where a product's factors cancel). Measured against
#: False (one process, interleaved, same hits; camera / incoherent /
#: shadow rays): Barth 1.17x / 1.11x / 1.09x, chmutov6 1.28x / 1.15x /
#: 1.47x, clebsch 1.31x / 1.18x / 1.10x, tangle 1.13x / 1.06x / 1.08x,
#: Kummer 1.13x / 1.00x / 1.11x, torus 1.02x / 0.99x / 1.11x.
APRIORI = True


def ray_polynomial(f: Expr, e, d, m):
    """([c_0 .. c_n], [w_0 .. w_n]): F(s) = f(e + s d) = sum c_k s^k up to
    |c_k - exact c_k| <= w_k (arrays of ``m``, float64; e, d: three arrays,
    exact). f must have a finite degree <= MAX_DEGREE."""
    deg = f.degree()
    if not deg <= MAX_DEGREE:
        raise ValueError(f"not a polynomial of degree <= {MAX_DEGREE} (degree {deg})")
    if APRIORI:
        return _ray_polynomial_apriori(f, e, d, m)
    return _ray_polynomial_running(f, e, d, m)


def _is_zero(v) -> bool:
    return isinstance(v, (int, float)) and v == 0


def _constant(n, m):
    """A constant (sub)expression's point value and error bound."""
    return evaluate_with_error(n, {}, {}, m)


def _is_constant(n, val) -> bool:
    return n.op != "var" and all(len(val[id(x)][0]) == 1 for x in n.args) \
        and (n.args or n.op in ("const", "named"))


def _ray_polynomial_apriori(f: Expr, e, d, m):
    """:func:`ray_polynomial` with a priori bounds. Each node holds its
    coefficients c, magnitudes M, the error E that the constants' own
    errors cause (None where they are exact, as literals and parameters
    are) and N, the most roundings on a path to any coefficient.

    Every computed coefficient is a sum of terms, each the exact term (of
    the computed constants and the exact ray) times at most N factors (1 +
    delta), |delta| <= u: so it is within gamma_N of the sum of the terms'
    magnitudes, M_k (the same expansion on |e|, |d| and the constants'
    magnitudes; gamma_N = N u / (1 - N u)). The constants' errors add E_k
    (propagated to first and second order: |a' b' - a b| <= M_a E_b + M_b
    E_a + E_a E_b). M's own rounding (relative, gamma_N) is in the final
    factor: w_k = (N u M_k + E_k)(1 + 4 N u)(1 + 2^-40)."""
    u = m.u
    val = {}
    for n in topological([f]):
        if n.op == "var" and n.param in ("x", "y", "z"):
            a = "xyz".index(n.param)
            val[id(n)] = ([e[a], d[a]], [m.abs(e[a]), m.abs(d[a])], None, 0)
        elif _is_constant(n, val):
            v, ev = _constant(n, m)
            val[id(n)] = ([v], [m.abs(v) + ev], None if _is_zero(ev) else [ev], 0)
        elif n.op in ("add", "sub"):
            (a, Ma, Ea, Na), (b, Mb, Eb, Nb) = (val[id(x)] for x in n.args)
            k = 1.0 if n.op == "add" else -1.0
            c, M = [], []
            for i in range(max(len(a), len(b))):
                if i >= len(b):
                    c.append(a[i]), M.append(Ma[i])
                elif i >= len(a):
                    c.append(k * b[i]), M.append(Mb[i])
                else:
                    c.append(a[i] + k * b[i]), M.append(Ma[i] + Mb[i])
            val[id(n)] = (c, M, _pad(_add_errors(Ea, Eb), len(c)), max(Na, Nb) + 1)
        elif n.op == "neg":
            a, Ma, Ea, Na = val[id(n.args[0])]
            val[id(n)] = ([-v for v in a], Ma, Ea, Na)
        elif n.op == "mul":
            val[id(n)] = _mul_apriori(val[id(n.args[0])], val[id(n.args[1])])
        elif n.op == "pow":
            val[id(n)] = _pow_apriori(val[id(n.args[0])], int(n.param))
        elif n.op == "div":              # by a constant (degree 0)
            (a, Ma, Ea, Na), (b, Mb, Eb, _) = (val[id(x)] for x in n.args)
            Ea = _pad(Ea, len(a))
            b = b[0]
            ab = m.abs(b)
            c = [ai / b for ai in a]
            M = [Mi / ab for Mi in Ma]
            if Eb is None:
                E = None if Ea is None else [Ei / ab for Ei in Ea]
            else:
                # a'/b' - a/b = (a' - a)/b' + a (b - b') / (b b'), |b| >= |b'| - e_b
                room = ab - Eb[0]
                E = []
                for i in range(len(a)):
                    ea = 0.0 if Ea is None else Ea[i]
                    E.append(m.select(room > 0, (ea + (Ma[i] + ea) * Eb[0] / room) / ab,
                                      math.inf))
            val[id(n)] = (c, M, E, Na + 1)
        else:
            raise ValueError(f"op {n.op!r} in a polynomial")
    c, M, E, N = val[id(f)]
    g = N * u
    up = (1.0 + 4.0 * g) * (1.0 + 2.0**-40)
    E = _pad(E, len(c))
    w = [g * Mk * up for Mk in M] if E is None else \
        [(g * Mk + Ek) * up for Mk, Ek in zip(M, E)]
    assert len(w) == len(c) == len(M)
    return list(c), w


def _add_errors(Ea, Eb):
    if Ea is None or Eb is None:
        return Eb if Ea is None else Ea
    Ea, Eb = _pad(Ea, len(Eb)), _pad(Eb, len(Ea))
    return [x + y for x, y in zip(Ea, Eb)]


def _pad(E, n: int):
    """E (the constants' errors of a coefficient list, or None) with zeros
    up to n coefficients."""
    return None if E is None else list(E) + [0.0] * (n - len(E))


def _mul_apriori(A, B):
    """Product of two (c, M, E, N): each c_k a sum of at most T products
    (T roundings on its longest path: the product and T - 1 additions)."""
    (a, Ma, Ea, Na), (b, Mb, Eb, Nb) = A, B
    Ea, Eb = _pad(Ea, len(a)), _pad(Eb, len(b))
    c, M, E = [], [], ([] if Ea is not None or Eb is not None else None)
    T = 0
    for k in range(len(a) + len(b) - 1):
        terms = [(i, k - i) for i in range(len(a)) if 0 <= k - i < len(b)]
        T = max(T, len(terms))
        s = mag = err = None
        for i, j in terms:
            p, q = a[i] * b[j], Ma[i] * Mb[j]
            s = p if s is None else s + p
            mag = q if mag is None else mag + q
            if E is not None:
                t = 0.0
                if Eb is not None:
                    t = Ma[i] * Eb[j]
                if Ea is not None:
                    t = t + Mb[j] * Ea[i]
                    if Eb is not None:
                        t = t + Ea[i] * Eb[j]
                err = t if err is None else err + t
        c.append(s), M.append(mag)
        if E is not None:
            E.append(err)
    return c, M, E, Na + Nb + T


def _pow_apriori(A, n: int):
    if n == 0:
        z = zero_like(A[0][0])
        return [z + 1.0], [z + 1.0], None, 0
    return powi(A, n, _mul_apriori)


def _ray_polynomial_running(f: Expr, e, d, m):
    """:func:`ray_polynomial` by running error analysis: each op's bound
    from its arguments' computed values and bounds."""
    u = m.u
    val = {}
    for n in topological([f]):
        if n.op == "var" and n.param in ("x", "y", "z"):
            a = "xyz".index(n.param)
            val[id(n)] = ([e[a], d[a]], [0.0, 0.0])
        elif _is_constant(n, val):
            # a constant (or a constant subexpression): its point value
            val[id(n)] = tuple([x] for x in _constant(n, m))
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
        z = zero_like(A[0][0])
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
