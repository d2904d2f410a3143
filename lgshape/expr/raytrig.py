"""A sum of products of sines and cosines of affine functions along a ray.

The triply periodic surfaces (the gyroid sin x cos y + sin y cos z + sin z
cos x, Schwarz's P and D, their level sets and weighted mixes) are such
sums. Along a ray e + t d, an affine L(x, y, z) is a + b t, and a product
of sines and cosines of such arguments is, by the product-to-sum rules, a
sum of sinusoids. So

    F(t) = f(e + t d) = C + sum_k A_k trig_k(alpha_k + omega_k t),

trig_k = sin or cos, with the phases alpha_k, frequencies omega_k and
amplitudes A_k computed once per ray (:func:`ray_sinusoids`). At any t,
one sine and cosine per sinusoid give F(t) and all its derivatives, and a
bound of |F'''| and |F''''| over the whole ray (sum |A_k| |omega_k|^3,
^4) is each form's remainder (:func:`forms`): F's and F''s quadratic
forms over |s - t| <= r without evaluating the expression again.

Errors: the ray is exact as given (the search's float64 ray); a, b and the
constants come with running error bounds (:mod:`.raypoly`, the point-error
rules), and the bounds of :func:`forms` cover the phases' and frequencies'
roundings, the library's sine and cosine (as :func:`lgshape.pointerror.e_periodic`)
and the sums. Anything NaN or infinite gives infinite or NaN bounds: no
information, never a wrong one.
"""
from __future__ import annotations

from dataclasses import dataclass

from .evaluate import evaluate_with_error
from .node import Expr, topological
from .raypoly import ray_polynomial

#: The most sinusoids a ray holds (a product of n factors gives 2^(n-1)).
MAX_SINUSOIDS = 32

_TRIG = ("sin", "cos")


@dataclass(frozen=True)
class Sinusoid:
    """sign * 2^-halves * coef * trig(sum of sign_i L_i)."""
    trig: str               # "sin" or "cos"
    sign: float             # +1 or -1
    halves: int
    coef: int               # index into TrigSum.coefs
    args: tuple             # ((sign_i, index into TrigSum.args), ...)


@dataclass(frozen=True)
class TrigSum:
    """f = constant + sum of :class:`Sinusoid` (see :func:`trig_sum`)."""
    constant: Expr
    coefs: tuple            # constant expressions
    args: tuple             # affine expressions L_i
    sinusoids: tuple


def trig_sum(f: Expr) -> TrigSum | None:
    """f as a constant plus terms c * prod_i trig_i(L_i), each c a constant
    expression, trig_i sin or cos and L_i affine in x, y, z (degree <= 1),
    through f's top-level +, -, negation and products by constants; the
    products expanded into sinusoids. None where f is not such a sum, holds
    no sine or cosine of x, y, z, or expands to over MAX_SINUSOIDS."""
    consts, coefs, args, out = [], [], [], []
    arg_index = {}
    stack = [(f, 1.0)]
    while stack:
        e, sign = stack.pop()
        if e.op in ("add", "sub"):
            stack.append((e.args[0], sign))
            stack.append((e.args[1], -sign if e.op == "sub" else sign))
            continue
        if e.op == "neg":
            stack.append((e.args[0], -sign))
            continue
        if e.degree() == 0:
            consts.append(Expr("neg", (e,)) if sign < 0 else e)
            continue
        factors, scale, todo = [], [], [e]
        while todo:
            n = todo.pop()
            if n.op == "mul":
                todo.extend(n.args)
            elif n.op == "neg":
                sign = -sign
                todo.append(n.args[0])
            elif n.degree() == 0:
                scale.append(n)
            elif n.op in _TRIG and n.args[0].degree() <= 1:
                factors.append(n)
            else:
                return None
        coef = Expr.lift(1.0)
        for c in scale:
            coef = Expr("mul", (coef, c))
        coefs.append(coef)
        terms = None
        for n in factors:
            i = arg_index.setdefault(id(n.args[0]), len(args))
            if i == len(args):
                args.append(n.args[0])
            terms = [(n.op, sign, 0, ((1.0, i),))] if terms is None else \
                [t for tr, s, h, a in terms for t in _times(tr, s, h, a, n.op, i)]
            if len(out) + len(terms) > MAX_SINUSOIDS:
                return None
        out.extend(Sinusoid(tr, s, h, len(coefs) - 1, a) for tr, s, h, a in terms)
    if not out:
        return None
    constant = Expr.lift(0.0)
    for c in consts:
        constant = Expr("add", (constant, c))
    return TrigSum(constant, tuple(coefs), tuple(args), tuple(out))


def _times(trig, sign, halves, arg, trig2, i):
    """trig(arg) * trig2(L_i) as two sinusoids (the product-to-sum rules):
    sin u sin v = (cos(u - v) - cos(u + v)) / 2, cos u cos v = (cos(u - v) +
    cos(u + v)) / 2, sin u cos v = (sin(u + v) + sin(u - v)) / 2, cos u sin v
    = (sin(u + v) - sin(u - v)) / 2."""
    plus, minus = arg + ((1.0, i),), arg + ((-1.0, i),)
    h = halves + 1
    if trig == trig2:
        s = -1.0 if trig == "sin" else 1.0
        return [("cos", sign, h, minus), ("cos", s * sign, h, plus)]
    s = 1.0 if trig == "sin" else -1.0
    return [("sin", sign, h, plus), ("sin", s * sign, h, minus)]


#: The float32 library's sine and cosine: their error (16 ulp of 1, as
#: arraymath's float32 eps_t) plus the argument's rounding to float32 and
#: its reduction (an ulp of |phi| each: 2^-23 |phi| with margin).
EPS_T32 = 2.0 ** -19
U32 = 2.0 ** -23


@dataclass
class RaySinusoids:
    """One ray's F (arrays, float64): the constant C; per sinusoid the
    amplitude A, phase alpha and frequency omega; and the bounds the forms
    need: the j-th derivative's error at t is within B[j] + S[j] |t|
    (j = 0..3); M3 and M4 bound F's third and fourth derivatives on the
    whole ray."""
    C: object
    A: list
    alpha: list
    omega: list
    B: list
    S: list
    M3: object
    M4: object


def ray_sinusoids(T: TrigSum, e, d, m) -> RaySinusoids:
    """F's sinusoids along rays e + t d (arrays of ``m``, float64; e, d
    exact), with their error bounds folded into per-ray constants.

    Per sinusoid, with a, b the ray's value and slope of its argument
    (errors e_alpha, e_omega) and Om = |omega| + e_omega >= |exact omega|:
    the phase phi = alpha + omega t is within e_alpha + e_omega |t| +
    2 u (|alpha| + |omega t|) of the exact one; float32 adds 2 U32 |phi| +
    EPS_T32 to its sine and cosine (Lipschitz 1), the sums (n + 4) u per
    term; the j-th derivative's omega^j is within j Om^(j-1) e_omega of the
    exact one. So the j-th derivative's error is within

        sum |A| Om^j (e_alpha + (2 u + 2.1 U32) |alpha| + EPS_T32 + (n+4) u)
          + e_A Om^j + j |A| Om^(j-1) e_omega                       (B[j])
        + |t| sum |A| Om^j (e_omega + (2 u + 2.1 U32) |omega|)      (S[j]).
    """
    u = m.u
    C, eC = evaluate_with_error(T.constant, {}, {}, m)
    coefs = [evaluate_with_error(c, {}, {}, m) for c in T.coefs]
    lines = []
    for L in T.args:
        c, w = ray_polynomial(L, e, d, m)
        lines.append((c[0], w[0], c[1], w[1]))
    n = len(T.sinusoids)
    k_phi = 2.0 * u + 2.1 * U32
    out = RaySinusoids(C, [], [], [], [eC, 0.0, 0.0, 0.0], [0.0] * 4, 0.0, 0.0)
    for s in T.sinusoids:
        A, eA = coefs[s.coef]
        k = s.sign * 0.5 ** s.halves            # exact: a sign and a power of 2
        A, eA = k * A, abs(k) * eA
        alpha, omega, ea, eo, ma, mo = None, None, 0.0, 0.0, 0.0, 0.0
        for sg, i in s.args:
            a, wa, b, wb = lines[i]
            alpha = sg * a if alpha is None else alpha + sg * a
            omega = sg * b if omega is None else omega + sg * b
            ea, eo = ea + wa, eo + wb
            ma, mo = ma + m.abs(a), mo + m.abs(b)
        ea = ea + len(s.args) * u * ma
        eo = eo + len(s.args) * u * mo
        out.A.append(A)
        out.alpha.append(alpha)
        out.omega.append(omega)
        aA = m.abs(A)
        Om = m.abs(omega) + eo
        base = ea + k_phi * m.abs(alpha) + EPS_T32 + (n + 4) * u
        slope = eo + k_phi * m.abs(omega)
        p_prev, p = 0.0, 1.0 + 0.0 * Om          # Om^(j-1), Om^j
        for j in range(4):
            out.B[j] = out.B[j] + aA * p * base + eA * p + j * aA * p_prev * eo
            out.S[j] = out.S[j] + aA * p * slope
            p_prev, p = p, p * Om
        out.M3 = out.M3 + aA * p_prev
        out.M4 = out.M4 + aA * p
    up = 1.0 + 8.0 * (n + 4) * u
    out.B = [v * up for v in out.B]
    out.S = [v * up for v in out.S]
    out.M3, out.M4 = out.M3 * up, out.M4 * up
    return out


def forms(seg, R: RaySinusoids, t, trig_of):
    """F's and F''s quadratic forms over |s| <= seg.r about t (float64),
    and F(t) with its error bound: (Qf, Qg, F, eF). ``trig_of``: per
    sinusoid, "sin" or "cos".

    A sine's j-th derivative at t is A omega^j times sin, cos, -sin, -cos
    of phi = alpha + omega t (a cosine's: cos, -sin, -cos, sin); the errors
    are B + S |t| (:class:`RaySinusoids`), the remainders M3 r^3 / 6 (F)
    and M4 r^3 / 6 (F')."""
    from .quadratic import Quad
    m, r = seg.m, seg.r
    u = m.u
    D = [None] * 4
    for A, alpha, omega, trig in zip(R.A, R.alpha, R.omega, trig_of):
        sn, cs = m.sincos32(alpha + omega * t)
        v = (sn, cs, -sn, -cs) if trig == "sin" else (cs, -sn, -cs, sn)
        pw = A
        for j in range(4):
            D[j] = v[j] * pw if D[j] is None else D[j] + v[j] * pw
            pw = pw * omega
    at = m.abs(t)
    E = [b + s * at for b, s in zip(R.B, R.S)]
    up = 1.0 + 16.0 * u
    F = R.C + D[0]
    eF = (E[0] + u * m.abs(F)) * up
    r2, r3 = seg.r2, seg.r3
    Rf = (R.M3 * r3 * (1.0 / 6.0) + eF + E[1] * r + 0.5 * E[2] * r2) * up
    Rg = (R.M4 * r3 * (1.0 / 6.0) + E[1] + E[2] * r + 0.5 * E[3] * r2) * up
    return Quad(F, D[1], 0.5 * D[2], Rf), Quad(D[1], D[2], 0.5 * D[3], Rg), F, eF
