"""A sum of products of sines and cosines of affine functions along a ray.

The triply periodic surfaces (the gyroid sin x cos y + sin y cos z + sin z
cos x, Schwarz's P and D, their level sets and weighted mixes) are such
sums. Along a ray e + t d, an affine L(x, y, z) is a + b t, and a product
of sines and cosines of such arguments is, by the product-to-sum rules, a
sum of sinusoids. So

    F(t) = f(e + t d) = C + sum_k A_k trig_k(alpha_k + omega_k t),

trig_k = sin or cos, with the phases alpha_k, frequencies omega_k and
amplitudes A_k computed once per ray (:func:`ray_sinusoids`). At any t,
one float32 sine and cosine per argument L_i give every sinusoid's (by
angle addition), hence F(t) and its derivatives, and a bound of the third
and fourth derivatives over the whole ray (sum |A_k| |omega_k|^3, ^4) is
each form's remainder (:func:`forms`): F's and F''s quadratic forms over
|s - t| <= r without evaluating the expression again.

Errors: the ray is exact as given (the search's float64 ray); a, b and the
constants come with running error bounds (:mod:`.raypoly`, the point-error
rules), and the bounds of :func:`forms` cover the phases' and frequencies'
roundings, the float32 sine and cosine (their library error and the
argument's rounding and reduction, as :func:`lgshape.pointerror.e_periodic`
models them), the angle additions and the sums. Anything NaN or infinite
gives infinite or NaN bounds: no information, never a wrong one.
"""
from __future__ import annotations

from dataclasses import dataclass

from ..arraymath import zero_like
from .evaluate import evaluate_with_error
from .node import Expr, product_chain
from .quadratic import Quad
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
        negated, scale, factors = product_chain(e, lambda n: n.degree() == 0)
        if negated:
            sign = -sign
        if not all(n.op in _TRIG and n.args[0].degree() <= 1 for n in factors):
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
    """One ray's F (arrays, float64): the constant C; per argument L_i its
    value a and slope b along the ray; per sinusoid the amplitude A and
    frequency omega; and the bounds the forms need: the j-th derivative's
    error at t is within B[j] + S[j] |t| (j = 0..3); M3 and M4 bound F's
    third and fourth derivatives on the whole ray."""
    C: object
    a: list
    b: list
    A: list
    omega: list
    B: list
    S: list
    M3: object
    M4: object


def ray_sinusoids(T: TrigSum, e, d, m) -> RaySinusoids:
    """F's sinusoids along rays e + t d (arrays of ``m``, float64; e, d
    exact), with their error bounds folded into per-ray constants.

    A test takes one float32 sine and cosine per argument, at phi_i = a_i +
    b_i t, and a sinusoid's by the angle-addition rules. With e_a, e_b the
    errors of a_i, b_i: phi_i is within e_a + e_b |t| + 2 u (|a_i| + |b_i
    t|) of the exact phase; float32 adds 2 U32 |phi_i| + EPS_T32 (Lipschitz
    1); each angle addition, of parts clamped to [-1, 1] (which moves no
    value away from the exact one), adds its two parts' errors and 4 u;
    the sum over sinusoids (n + 4) u a term. So a sinusoid's sine and
    cosine are within base + slope |t| of the exact ones, base = sum_i (e_a
    + k |a_i| + EPS_T32) + 4 u (k_i + 1) (k_i arguments), slope = sum_i
    (e_b + k |b_i|), k = 2 u + 2.1 U32; with Om = |omega| + e_omega >=
    |exact omega|,
    the j-th derivative's error is within

        sum |A| Om^j (base + (n + 4) u) + e_A Om^j + j |A| Om^(j-1) e_omega
          + |t| sum |A| Om^j slope.
    """
    u = m.u
    C, eC = evaluate_with_error(T.constant, {}, {}, m)
    coefs = [evaluate_with_error(c, {}, {}, m) for c in T.coefs]
    n = len(T.sinusoids)
    k_phi = 2.0 * u + 2.1 * U32
    out = RaySinusoids(C, [], [], [], [], [eC, 0.0, 0.0, 0.0], [0.0] * 4, 0.0, 0.0)
    errs = []           # per argument: (phase error at t = 0, its growth, e_b)
    for L in T.args:
        c, w = ray_polynomial(L, e, d, m)
        out.a.append(c[0])
        out.b.append(c[1])
        errs.append((w[0] + k_phi * m.abs(c[0]) + EPS_T32, w[1] + k_phi * m.abs(c[1]), w[1]))
    for s in T.sinusoids:
        A, eA = coefs[s.coef]
        k = s.sign * 0.5 ** s.halves            # exact: a sign and a power of 2
        A, eA = k * A, abs(k) * eA
        omega, eo, mo = None, 0.0, 0.0
        base, slope = 4.0 * u * (len(s.args) + 1), 0.0
        for sg, i in s.args:
            b = out.b[i]
            omega = sg * b if omega is None else omega + sg * b
            mo = mo + m.abs(b)
            base, slope, eo = base + errs[i][0], slope + errs[i][1], eo + errs[i][2]
        eo = eo + len(s.args) * u * mo
        base = base + (n + 4) * u
        out.A.append(A)
        out.omega.append(omega)
        aA = m.abs(A)
        Om = m.abs(omega) + eo
        p_prev, p = 0.0, 1.0 + zero_like(Om)          # Om^(j-1), Om^j
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


def _phase_sincos(k: Sinusoid, sc, clamp=None):
    """Sine and cosine of sinusoid k's phase (sum of sign_i phi_i) from
    each argument's (``sc``), by angle addition; ``clamp``: applied to an
    addition's result before it is a part of the next one."""
    sn = cs = None
    for j, (sg, i) in enumerate(k.args):
        si, ci = sc[i]
        if sg < 0:
            si = -si
        if j == 0:
            sn, cs = si, ci
            continue
        if clamp is not None and j >= 2:
            sn, cs = clamp(sn), clamp(cs)
        sn, cs = sn * ci + cs * si, cs * ci - sn * si
    return sn, cs


def forms(seg, R: RaySinusoids, t, sinusoids):
    """F's and F''s quadratic forms over |s| <= seg.r about t (float64),
    and F(t) with its error bound: (Qf, Qg, F, eF). ``sinusoids``: the
    :class:`TrigSum`'s.

    A sine's j-th derivative at t is A omega^j times sin, cos, -sin, -cos
    of its phase (a cosine's: cos, -sin, -cos, sin), whose sine and cosine
    come from the arguments' by angle addition; the errors are B + S |t|
    (:class:`RaySinusoids`), the remainders M3 r^3 / 6 (F) and M4 r^3 / 6
    (F')."""
    m, r = seg.m, seg.r
    u = m.u
    def clamp(v):
        return m.minimum(m.maximum(v, -1.0), 1.0)
    sc = [tuple(clamp(v) for v in m.sincos32(a + b * t)) for a, b in zip(R.a, R.b)]
    D = [None] * 4
    for A, omega, k in zip(R.A, R.omega, sinusoids):
        sn, cs = _phase_sincos(k, sc, clamp)
        v = (sn, cs, -sn, -cs) if k.trig == "sin" else (cs, -sn, -cs, sn)
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


def value_and_slope(m, R: RaySinusoids, t, sinusoids):
    """F(t) and F'(t) in m's precision (float64 for Newton's steps), no
    error bounds: one sine and cosine per argument, the sinusoids' by angle
    addition."""
    sc = [m.sincos(a + b * t) for a, b in zip(R.a, R.b)]
    F, g = R.C + zero_like(t), zero_like(t)
    for A, omega, k in zip(R.A, R.omega, sinusoids):
        sn, cs = _phase_sincos(k, sc)
        v, dv = (sn, cs) if k.trig == "sin" else (cs, -sn)
        F = F + A * v
        g = g + A * omega * dv
    return F, g
