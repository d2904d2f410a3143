"""Rays parallel to the flat faces of boxes and rounded boxes in unions.

A ray with a direction component exactly 0 (or 1e-8) along a box's face,
1e-7 to 1e-2 of the diagonal off it, sees F constant (or nearly) all along
the face: only a bound of F's slope there (the mean-value form) excludes
the face's stretch. The slope of the distance sqrt(sum max(q_i, 0)^2) is
U' / (2 sqrt U), whose interval rule is unbounded wherever U's range
reaches 0 (max(q, 0) = 0, or q's sign unknown to float32 rounding: the
ray is within rounding of the face's plane); such rays were split to the
minimum width along the whole face and capped at 4096 iterations.
:func:`lgshape.expr.quadratic._norm_bound` bounds that quotient by
Cauchy-Schwarz, |sum_i v_i v_i'| / |v| <= |v'|.

The oracle is independent of the kernels: each part's solid along the very
float32 ray (promoted exactly to float64), in float64: a sharp box by the
slab method, a rounded box (convex, so its signed distance is convex along
a line) from the minimum of its exact signed distance (golden section) and
bisection to full precision on each side, a torus from its quartic's roots
(numpy.roots, polished by Newton), merged into the union's boundary points.
All parameters are dyadic numbers, so the float32 rows the builders store
are the oracle's exactly (the inner half sizes h - rounding too).

Judged as the contract has it (lgshape.trace): a first root with a float64
sign change across it, isolated by twice the smallest interval (2e-6 of the
diagonal) from the other boundary points and the ray's start, must be hit;
a first root that is not (a sliver, a tangent pair) may be hit or missed,
and a hit must lie at a boundary point up to the first isolated one. No
hit where there is no root, none before the first root, no ray capped.

The tolerance on t. The search refines a bracket in float64 until the step,
or the proven distance |F| / min |g|, is below tol = 1e-6 diag / |d| (the
contract's), so |t64 - t*| <= tol, t* the exact root of the float32 ray
(the oracle's, computed with float64 errors of ~1e-16 relative, far below
tol). The float32 t adds its own rounding to nearest, ulp(t) / 2 <= 2^-24
|t|. The float32 ray (origin and direction) and the float32 parameters are
the oracle's own, so they add nothing. Bound: |t - t*| <= tol + 2^-24 |t|
(plus 1e-12 |t| for the oracle's float64 evaluation), which is what is
asserted; both t64 and t are checked.
"""
from __future__ import annotations

import functools

import numpy as np
import pytest

import lgshape
import lgshape.primitives as P

REL_TOL = 1e-6          # the contract's refinement tolerance, x diagonal
REL_ISOLATED = 2e-6     # twice the smallest interval, x diagonal
OFFSETS = 10.0 ** np.arange(-7.0, -1.0)     # x diagonal, each outward and inward
TILT = 1e-8             # the off-axis component of the tilted rays


def _dyadic(v, bits=10):
    """v rounded to a multiple of 2^-bits (exact in float32, and so are the
    differences the builders store)."""
    return np.round(np.asarray(v, np.float64) * 2.0 ** bits) / 2.0 ** bits


@functools.lru_cache(maxsize=None)
def scene(seed=19, nb=8, nr=8, nt=6):
    """nb sharp boxes, nr rounded boxes (roundings from 2^-20 to 1/4 of the
    smallest half size) and nt tori, dyadic, in [-0.7, 0.7]^3."""
    rng = np.random.default_rng(seed)
    cb = _dyadic(rng.uniform(-0.7, 0.7, (nb + nr, 3)))
    hb = _dyadic(rng.uniform(0.05, 0.2, (nb + nr, 3)))
    rr = np.zeros(nb + nr)
    rr[nb:] = _dyadic(hb[nb:].min(1) * np.array([0.25, 0.1, 0.02, 2.0 ** -10, 2.0 ** -14, 2.0 ** -20,
                                                0.2, 0.05][:nr]), 24)
    ct = _dyadic(rng.uniform(-0.7, 0.7, (nt, 3)))
    R = _dyadic(rng.uniform(0.1, 0.2, nt))
    r = _dyadic(R * rng.uniform(0.15, 0.4, nt))
    return cb, hb, rr, ct, R, r


def parts(cb, hb, rr, ct, R, r):
    out = [P.boxes(cb, hb, rounding=rr)]
    if len(ct):
        out.append(P.tori(ct, R, r))
    return out


# ---------------------------------------------------------------------------
# the oracle (float64)
# ---------------------------------------------------------------------------

def _slab(o, d, lo, hi):
    """[a, b] of the ray in the box [lo, hi] (a > b: none); d = 0 exactly on
    an axis: inside or not on that axis."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - o) / d, (hi - o) / d
    flat = d == 0
    inside = (o >= lo) & (o <= hi)
    a = np.where(flat, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2))
    b = np.where(flat, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2))
    return a.max(-1), b.min(-1)


def _rounded_sd(p, c, e, rr):
    q = np.abs(p - c) - e
    return np.linalg.norm(np.maximum(q, 0), axis=-1) + np.minimum(q.max(-1), 0) - rr


def rounded_box_interval(o, d, c, h, rr):
    """The rounded box's solid along each ray: its signed distance is convex
    along the line, so its minimum (golden section over the ray's part in
    the box c +- h, which holds the solid) and a bisection on either side
    give the two boundary points."""
    e = h - rr
    a, b = _slab(o, d, c - h, c + h)
    ok = a <= b
    a, b = np.where(ok, a, 0.0), np.where(ok, b, 0.0)

    def F(t):
        return _rounded_sd(o + t[:, None] * d, c, e, rr)
    lo, hi = a.copy(), b.copy()
    g = (np.sqrt(5.0) - 1) / 2
    x1, x2 = hi - g * (hi - lo), lo + g * (hi - lo)
    f1, f2 = F(x1), F(x2)
    for _ in range(120):
        left = f1 < f2
        hi = np.where(left, x2, hi)
        lo = np.where(left, lo, x1)
        x2n = np.where(left, x1, lo + g * (hi - lo))
        x1n = np.where(left, hi - g * (hi - lo), x2)
        f2n = np.where(left, f1, np.nan)
        f1n = np.where(left, np.nan, f2)
        x1, x2 = x1n, x2n
        f1 = np.where(np.isnan(f1n), F(x1), f1n)
        f2 = np.where(np.isnan(f2n), F(x2), f2n)
    tm = 0.5 * (lo + hi)
    ok &= F(tm) < 0

    def root(u, v, inside_at_v):
        # F(u) >= 0 > F(v) (inside_at_v) or F(u) < 0 <= F(v)
        for _ in range(200):
            w = 0.5 * (u + v)
            neg = F(w) < 0
            move_v = neg if inside_at_v else ~neg
            u, v = np.where(move_v, u, w), np.where(move_v, w, v)
        return 0.5 * (u + v)
    t_in = root(a, tm, True)
    t_out = root(tm, b, False)
    return np.where(ok, t_in, np.inf), np.where(ok, t_out, -np.inf)


def torus_intervals(o, d, c, R, r):
    out = []
    for i in range(len(o)):
        p, q = o[i] - c, d[i]
        a2, a1, a0 = q @ q, 2 * p @ q, p @ p + R * R - r * r
        b2, b1, b0 = q[:2] @ q[:2], 2 * p[:2] @ q[:2], p[:2] @ p[:2]
        co = np.polymul([a2, a1, a0], [a2, a1, a0])
        co[2:] -= 4 * R * R * np.array([b2, b1, b0])
        rt = np.roots(co)
        rt = rt[np.abs(rt.imag) <= 1e-7 * (1 + np.abs(rt.real))].real
        dco = np.polyder(co)
        for _ in range(4):                      # Newton polish
            dv = np.polyval(dco, rt)
            rt = np.where(dv != 0, rt - np.polyval(co, rt) / np.where(dv != 0, dv, 1.0), rt)
        rt = np.sort(rt)
        iv = []
        for k in range(len(rt) - 1):
            x = p + 0.5 * (rt[k] + rt[k + 1]) * q
            if (np.hypot(x[0], x[1]) - R) ** 2 + x[2] ** 2 < r * r:
                iv.append((rt[k], rt[k + 1]))
        out.append(iv)
    return out


def union_pieces(sc, o, d):
    """Per ray, the union's solid along it as merged [a, b] pieces."""
    cb, hb, rr, ct, R, r = sc
    n = len(o)
    ivs = [[] for _ in range(n)]
    for c, h, k in zip(cb, hb, rr):
        a, b = _slab(o, d, c - h, c + h) if k == 0 else rounded_box_interval(o, d, c, h, k)
        for i in np.flatnonzero(a <= b):
            ivs[i].append((a[i], b[i]))
    for c, RR, rrr in zip(ct, R, r):
        for i, iv in enumerate(torus_intervals(o, d, c, RR, rrr)):
            ivs[i].extend(iv)
    out = []
    for iv in ivs:
        merged = []
        for a, b in sorted(iv):
            if merged and a <= merged[-1][1]:
                merged[-1][1] = max(merged[-1][1], b)
            else:
                merged.append([a, b])
        out.append(merged)
    return out


def judge(surf, sc, o32, d32, res):
    """Counts (capped, false, missed, wrong t) and the worst |t - t*| / tol,
    under the contract's allowances (module text)."""
    o, d = o32.astype(np.float64), d32.astype(np.float64)
    diag = surf.diagonal
    dn = np.linalg.norm(d, axis=1)
    tol = REL_TOL * diag / dn
    iso = REL_ISOLATED * diag / dn
    lo, hi = np.asarray(surf.lo, np.float64), np.asarray(surf.hi, np.float64)
    t0, t1 = _slab(o, d, lo, hi)
    t0 = np.maximum(t0, 0.0)
    pieces = union_pieces(sc, o, d)
    t64 = np.asarray(res.t64, np.float64)
    t32 = np.asarray(res.t, np.float64)
    hit = np.asarray(res.hit, bool)
    capped = np.asarray(res.capped, bool)
    false = missed = wrong = 0
    worst = 0.0
    bad = []
    for i in range(len(o)):
        # boundary points in the searched segment, each with whether it is
        # isolated (a float64 sign change with room around it)
        pts = []
        for a, b in pieces[i]:
            for t in (a, b):
                if t0[i] - tol[i] <= t <= t1[i] + tol[i] and np.isfinite(t):
                    pts.append(t)
        pts = np.sort(np.array(pts))
        gaps = np.diff(np.concatenate([[t0[i]], pts, [t1[i]]]))
        isolated = (gaps[:-1] >= iso[i]) & (gaps[1:] >= iso[i]) if len(pts) else np.zeros(0, bool)
        ver = np.flatnonzero(isolated)
        upto = pts[:ver[0] + 1] if len(ver) else pts
        if hit[i]:
            err = np.abs(upto - t64[i]).min() if len(upto) else np.inf
            err32 = np.abs(upto - t32[i]).min() if len(upto) else np.inf
            lim32 = tol[i] + 2.0 ** -24 * abs(t32[i]) + 1e-12 * abs(t32[i])
            if not np.isfinite(err):
                false += 1
                bad.append((i, "false hit", t64[i], pts[:3]))
            elif err > tol[i] * (1 + 1e-9) + 1e-12 * abs(t64[i]) or err32 > lim32:
                if len(pts) and t64[i] < pts[0] - tol[i]:
                    false += 1
                    bad.append((i, "hit before the first root", t64[i], pts[:3]))
                else:
                    wrong += 1
                    bad.append((i, "t off", t64[i], t32[i], upto[:3], err / tol[i]))
            else:
                worst = max(worst, err / tol[i], (err32 - 2.0 ** -24 * abs(t32[i])) / tol[i])
        elif len(ver):
            missed += 1
            bad.append((i, "missed", pts[:3]))
    return int(capped.sum()), false, missed, wrong, worst, bad


# ---------------------------------------------------------------------------
# rays along the faces
# ---------------------------------------------------------------------------

def face_rays(sc, diag, seed=5, faces_per_box=2):
    """For every box, random faces: a point on the face's flat part, moved
    off it by each offset (outward and inward), a direction along one of
    the face's two axes (either way), exactly and tilted by TILT off it
    (toward the face's normal and the other axis), from 0.05 to 0.6
    diagonals back. And for every torus, rays in the plane of its top
    (z = c + r), off it by the offsets, along x or y over a point of the
    tube's top circle."""
    cb, hb, rr, ct, R, r = sc
    rng = np.random.default_rng(seed)
    O, D = [], []
    for c, h, k in zip(cb, hb, rr):
        for _ in range(faces_per_box):
            ax = rng.integers(3)
            side = rng.choice([-1.0, 1.0])
            b = (ax + 1 + rng.integers(2)) % 3
            other = 3 - ax - b
            for off in OFFSETS * diag:
                for s in (1.0, -1.0):
                    for tilt in (0.0, TILT):
                        p = c.copy()
                        # on the flat part of the face (the rounding's inside)
                        p[other] += rng.uniform(-1, 1) * (h[other] - k) * 0.9
                        p[ax] += side * (h[ax] + s * off)
                        dd = np.zeros(3)
                        dd[b] = rng.choice([-1.0, 1.0])
                        if tilt:
                            dd[ax] = tilt * rng.choice([-1.0, 1.0])
                            dd[other] = tilt * rng.uniform(-1, 1)
                        dd /= np.linalg.norm(dd)
                        O.append(p - rng.uniform(0.05, 0.6) * diag * dd)
                        D.append(dd)
    for c, RR, rrr in zip(ct, R, r):
        for off in OFFSETS * diag:
            for s in (1.0, -1.0):
                for tilt in (0.0, TILT):
                    ang = rng.uniform(0, 2 * np.pi)
                    p = c + np.array([RR * np.cos(ang), RR * np.sin(ang), rrr + s * off])
                    dd = np.zeros(3)
                    dd[rng.integers(2)] = 1.0
                    dd[2] = tilt
                    dd /= np.linalg.norm(dd)
                    O.append(p - rng.uniform(0.3, 0.6) * diag * dd)
                    D.append(dd)
    d32 = np.float32(np.array(D))
    # the exact zeros stay zeros; the tilted components stay ~1e-8
    return np.float32(np.array(O)), d32


def _message(res, counts, it):
    capped, false, missed, wrong, worst, bad = counts
    return (f"capped {capped}, false {false}, missed {missed}, wrong t {wrong}, worst |t - t*| "
            f"{worst:.3f} tol, max iterations {int(it.max())}, mean {it.mean():.1f}; e.g. {bad[:3]}")


CASES = {
    # the table path: 22 parts
    "table": (dict(), True),
    # the fused expression (no tables): 2 sharp boxes, 2 rounded, 1 torus
    "fused": (dict(seed=23, nb=2, nr=2, nt=1), False),
}


@functools.lru_cache(maxsize=None)
def traced(case):
    kw, tables = CASES[case]
    sc = scene(**kw)
    surf = lgshape.Surface(P.union(*parts(*sc)), tables=tables)
    assert (surf.tables is not None) == tables
    o, d = face_rays(sc, surf.diagonal)
    res = surf.trace(o, d)
    return sc, surf, o, d, res


@pytest.mark.parametrize("case", sorted(CASES))
def test_axis_parallel_faces(case):
    sc, surf, o, d, res = traced(case)
    counts = judge(surf, sc, o, d, res)
    it = np.asarray(res.iterations)
    msg = _message(res, counts, it)
    capped, false, missed, wrong, worst, bad = counts
    assert (d == 0).any(1).mean() > 0.45, "too few rays with an exact zero component"
    assert capped == 0, msg
    assert false == 0, msg
    assert missed == 0, msg
    assert wrong == 0, msg
    # none near the cap (4096): the face's stretch is excluded in a few tests
    assert it.max() < 600, msg


def _distance_text(kind, row):
    """The builders' signed distances as text (their formulas, with squares
    as powers): a box c +- (e + rr) rounded by rr; a torus (c, R, r)."""
    c = row[:3]
    off = [f"({v} - {c[i]!r})" for i, v in enumerate("xyz")]
    if kind == "box":
        q = [f"abs({off[i]}) - {row[3 + i]!r}" for i in range(3)]
        outside = " + ".join(f"max({v}, 0)^2" for v in q)
        return f"sqrt({outside}) + min(max({', '.join(q)}), 0) - {row[6]!r}"
    return f"sqrt((sqrt({off[0]}^2 + {off[1]}^2) - {row[3]!r})^2 + {off[2]}^2) - {row[4]!r}"


def test_slope_bound_encloses():
    """The Cauchy-Schwarz form of U' / (2 sqrt U) encloses g: the quadratic
    forms of the box's and torus's slopes over random segments (many along
    an axis, near faces and the torus's axis) against float64 point values
    at 33 points of each."""
    from lgshape.arraymath import DrJitMath, NUMPY
    from lgshape.expr import evaluate
    from lgshape.expr.diff import DX, DY, DZ, derivative
    from lgshape.expr.quadratic import evaluate_quadratic, quad_env, quad_range
    from lgshape.expr import parse
    from conftest import JIT
    Float = JIT.Float32
    m = DrJitMath(Float)
    rng = np.random.default_rng(3)
    n = 2000
    seeds = {"x": DX, "y": DY, "z": DZ}
    for kind, row in (("box", [0.1, -0.2, 0.05, 0.2, 0.15, 0.1, 0.0]),
                      ("box", [0.1, -0.2, 0.05, 0.15, 0.1, 0.05, 0.05]),
                      ("torus", [0.0, 0.1, -0.1, 0.3, 0.1])):
        row = [float(np.float32(v)) for v in row]
        g = derivative(parse(_distance_text(kind, row)), seeds)
        c = np.array(row[:3])
        e = c + rng.uniform(-0.5, 0.5, (n, 3)) * np.array(row[3:6] if kind == "box" else [0.5, 0.5, 0.2])
        if kind == "box":
            # half the segments start on or near a face plane, along it
            ax = rng.integers(0, 3, n)
            near = rng.uniform(0, 1, n) < 0.5
            h = np.array(row[3:6]) + row[6]
            e[near, ax[near]] = c[ax[near]] + rng.choice([-1, 1], near.sum()) * (
                h[ax[near]] + 10.0 ** rng.uniform(-8, -2, near.sum()) * rng.choice([-1, 1], near.sum()))
        else:
            near = rng.uniform(0, 1, n) < 0.5        # through or near the axis
            e[near, :2] = c[:2] + 10.0 ** rng.uniform(-8, -2, (near.sum(), 2))
        dd = rng.normal(size=(n, 3))
        zero = rng.uniform(0, 1, (n, 3)) < 0.4
        dd = np.where(zero, np.where(rng.uniform(0, 1, (n, 3)) < 0.5, 0.0, 1e-8 * dd), dd)
        dd[(dd == 0).all(1), 0] = 1.0
        dd /= np.linalg.norm(dd, axis=1, keepdims=True)
        e32, d32 = np.float32(e), np.float32(dd)
        half = np.float32(10.0 ** rng.uniform(-6, -1, n))
        seg, env = quad_env(m, [Float(e32[:, i]) for i in range(3)], [Float(d32[:, i]) for i in range(3)],
                            Float(-half), Float(half))
        (Qg,) = evaluate_quadratic([g], env, seg)
        rg = quad_range(seg, Qg)
        glo, ghi = np.asarray(rg.lo, np.float64), np.asarray(rg.hi, np.float64)
        finite = np.isfinite(glo) & np.isfinite(ghi)
        assert finite.mean() > 0.99, (kind, finite.mean())
        e64, d64 = e32.astype(np.float64), d32.astype(np.float64)
        for s in np.linspace(-1, 1, 33):
            p = e64 + (s * half.astype(np.float64))[:, None] * d64
            env64 = {v: p[:, i] for i, v in enumerate("xyz")}
            env64.update({"d" + v: d64[:, i] for i, v in enumerate("xyz")})
            with np.errstate(all="ignore"):
                gv = np.asarray(evaluate(g, env64, NUMPY), np.float64)
            ok = ~np.isfinite(gv) | ~finite | ((gv >= glo - 1e-12) & (gv <= ghi + 1e-12))
            assert ok.all(), (kind, s, np.flatnonzero(~ok)[:5], gv[~ok][:5], glo[~ok][:5], ghi[~ok][:5])
        # along a face's plane (a zero component), within rounding of it or
        # off it, the slope bound is mostly the float32 underflow floor
        # (F is constant there, to rounding)
        if kind == "box":
            flat = near & (d32[np.arange(n), ax] == 0)
            w = np.maximum(np.abs(glo), np.abs(ghi))[flat]
            assert np.median(w) < 1e-30, np.median(w)
