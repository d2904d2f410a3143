"""Float64 oracles for the ray-search tests (test_11, test_12).

:func:`check_first_roots` holds the kernel's answers against all roots of
F(t) = f(o + t d) along each ray, given by the caller in float64 (companion
matrix eigenvalues from :func:`lgshape.reference.polynomial_roots`, or closed
forms), for the very float32 rays the kernel saw (converted to float64, so
the ray inputs add nothing to the error).

The tolerance is the documented one (:mod:`lgshape.trace`): the search
refines a root until the step or the proven distance is below 1e-6 of the
box diagonal, ``tol = 1e-6 * diag / |d|`` in t, checked on ``RayResult.t64``
(float64, before rounding); ``t`` must be ``t64`` rounded to float32.

Each ray is classed by its candidate roots: roots with |Im t| < delta
(delta = 1e-4 x diag, a neighbourhood scale, not a tolerance on t) and Re t
in [t0 - tol, t1 + tol], sorted. A candidate c is *verified* (a real simple
root, proven in float64) when its bracket half width h = min(delta, half the
gaps to its neighbours, c - t0, t1 - c) is at least H_MIN = 2e-6 x diag and
F(c - h), F(c + h) have opposite signs, both above a float64 noise floor
(1e-12 x max |F| along the segment): only that candidate lies in the
bracket, so the bracket holds an odd number of real roots, one. H_MIN is
twice the kernel's minimum interval half width (1e-6 x diag), so no
minimum-width interval can hold c and a neighbour: the contract promises
the first root of every such ray.

- ``none``: no candidate -> must be a miss.
- the first candidate is verified -> must be a hit with |t64 - r| <= tol, r
  the candidate polished by float64 bisection in its bracket. Sub-classes
  (counted): ``simple`` (h = delta: isolated by 2 delta, away from the ends,
  with |F(c +- delta)| above the float32 noise level 1e-5 (1 + max |F|), the
  previous suite's definition; these must also be resolved by the
  monotonicity test: ``unresolved`` False), ``pair`` (a neighbour within 2
  delta: the close root pairs of thin slivers), ``end`` (within delta of t0
  or t1), ``faint`` (isolated, but F(c +- delta) below the float32 level).
- ``tangent``, the allowance: the first candidate is not verified (a
  near-tangent complex pair, a near-double root closer than 2 H_MIN, a root
  within H_MIN of the range ends). The kernel may report such a touch or not
  (tangent touches go either way, see :mod:`lgshape.trace`): a hit must lie
  within tol + |Im c| of a candidate c that is not after the first verified
  one, and where a verified root exists the ray must hit. Callers bound the
  count of these rays.
No other hit is allowed: a hit anywhere else is a false hit.
"""
from __future__ import annotations

import numpy as np

from lgshape.reference import along, clip_to_box

REL_TOL = 1e-6        # documented refinement tolerance, x diagonal (trace.py)
REL_DELTA = 1e-4      # classification neighbourhood, x diagonal
REL_H_MIN = 2e-6      # 2 x the kernel's minimum interval half width
NOISE32 = 1e-5        # the float32 margin of the ``simple`` class
NOISE64 = 1e-12       # the float64 floor for a verified sign change

CLASSES = ("simple", "pair", "end", "faint", "none", "tangent")


def bisect(F, o, d, a, b, steps=40):
    """The sign change of F in [a, b] (F(a), F(b) of opposite signs) by
    float64 bisection (brackets here are at most 2e-4 x diag wide: 40 halvings
    leave 2e-16 x diag)."""
    fa = along(F, o, d, a)
    for _ in range(steps):
        m = 0.5 * (a + b)
        fm = along(F, o, d, m)
        left = np.sign(fm) * np.sign(fa) <= 0
        a, fa, b = np.where(left, a, m), np.where(left, fa, fm), np.where(left, m, b)
    return 0.5 * (a + b)


def check_first_roots(surf, F, o32, d32, roots, groups=None, res=None, t_min=0.0):
    """Hold ``surf.trace(o32, d32, t_min)`` (or ``res``) against ``roots``
    ((n, k) complex, all roots of F along each float32 ray, NaN where none).
    Raises AssertionError naming each class and group; returns the per-class
    counts (dict, plus ``rays`` and ``tangent_hits``)."""
    n = len(o32)
    groups = np.repeat(["rays"], n) if groups is None else np.asarray(groups)
    res = surf.trace(o32, d32, t_min=t_min) if res is None else res
    t32 = np.asarray(res.t, np.float32)
    t64 = np.asarray(res.t64, np.float64)
    hit, unres = np.asarray(res.hit), np.asarray(res.unresolved)
    capped = np.asarray(res.capped)
    assert not capped.any(), f"{int(capped.sum())} rays reached the iteration bound"
    # t is t64 rounded to float32 (documented: Mitsuba's float32 t).
    assert np.array_equal(t32[hit], t64[hit].astype(np.float32)), "t is not t64 rounded to float32"
    assert np.all(np.isinf(t64[~hit])), "a miss with a finite t64"

    o, d = o32.astype(np.float64), d32.astype(np.float64)
    diag = float(np.linalg.norm(surf.hi - surf.lo))
    tol = REL_TOL * diag / np.linalg.norm(d, axis=1)
    delta, h_min = REL_DELTA * diag, REL_H_MIN * diag
    t0, t1 = clip_to_box(o, d, surf.lo, surf.hi, t_min)
    ok = t1 > t0
    with np.errstate(all="ignore"):
        roots = np.asarray(roots, complex)
        cand = (ok[:, None] & np.isfinite(roots) & (np.abs(roots.imag) < delta)
                & (roots.real >= (t0 - tol)[:, None]) & (roots.real <= (t1 + tol)[:, None]))
        key = np.where(cand, roots.real, np.inf)
        order = np.argsort(key, 1)
        c = np.take_along_axis(key, order, 1)
        im = np.take_along_axis(np.abs(roots.imag), order, 1)
        has = np.isfinite(c)
        # Magnitude of F along the segment, for the noise floors.
        s9 = np.linspace(0, 1, 9)
        tt = np.where(ok, t0, 0)[:, None] + np.where(ok, t1 - t0, 0)[:, None] * s9[None]
        M = np.nanmax(np.abs(along(F, o, d, tt)), 1)
        gap_prev = np.diff(np.concatenate([np.full((n, 1), -np.inf), c], 1), axis=1)
        gap_next = np.diff(np.concatenate([c, np.full((n, 1), np.inf)], 1), axis=1)
        gap_prev = np.where(np.isnan(gap_prev), np.inf, gap_prev)
        gap_next = np.where(np.isnan(gap_next), np.inf, gap_next)
        h = np.minimum.reduce([np.full(c.shape, delta), gap_prev / 2, gap_next / 2,
                               c - t0[:, None], t1[:, None] - c])
        h = np.where(has, h, 0.0)
        cs = np.where(has, c, 0.0)
        fm, fp = along(F, o, d, cs - h), along(F, o, d, cs + h)
        mag = np.minimum(np.abs(fm), np.abs(fp))
        verified = has & (h >= h_min) & (np.sign(fm) * np.sign(fp) < 0) & (mag > NOISE64 * (1 + M[:, None]))

    none = ~has[:, 0]
    first = verified[:, 0]
    r = np.full(n, np.nan)
    if first.any():
        k = np.flatnonzero(first)
        r[k] = bisect(F, o[k], d[k], c[k, 0] - h[k, 0], c[k, 0] + h[k, 0])
    simple = first & (h[:, 0] == delta) & (mag[:, 0] > NOISE32 * (1 + M))
    pair = first & ~simple & (gap_next[:, 0] < 2 * delta)
    end = first & ~simple & ~pair & ((c[:, 0] - t0 < delta) | (t1 - c[:, 0] < delta))
    faint = first & ~simple & ~pair & ~end
    tangent = has[:, 0] & ~first

    at_r = hit & (np.abs(t64 - r) <= tol)
    wrong = first & ~at_r                              # missed, or hit elsewhere
    unres_simple = simple & unres
    false_none = none & hit
    # The allowance: a hit at a candidate up to the first verified one.
    any_ver = verified.any(1)
    k_ver = np.where(any_ver, np.argmax(verified, 1), c.shape[1] - 1)
    upto = np.arange(c.shape[1])[None] <= k_ver[:, None]
    with np.errstate(invalid="ignore"):
        near = (np.abs(c - t64[:, None]) <= tol[:, None] + im) & has & upto
    tangent_bad = tangent & np.where(hit, ~near.any(1), any_ver)

    counts = {k_: int(v.sum()) for k_, v in zip(CLASSES, (simple, pair, end, faint, none, tangent))}
    counts.update(rays=n, tangent_hits=int((tangent & hit).sum()))
    classes = dict(zip(CLASSES, (simple, pair, end, faint, none, tangent)))
    counts["by_group"] = {g: {k_: int(v[groups == g].sum()) for k_, v in classes.items()}
                          for g in dict.fromkeys(groups)}
    err = np.abs(t64 - r)[first & hit] / (tol[first & hit] / REL_TOL)

    def by_group(mask):
        return ", ".join(f"{g} {int(mask[groups == g].sum())}" for g in dict.fromkeys(groups))
    msg = (f"classes {counts['by_group']}; max |t64 - r| on verified first roots: "
           f"{(err.max() if err.size else 0):.2e} x diag (tol {REL_TOL:g}); "
           f"first root missed or wrong t: {by_group(wrong)} "
           f"[simple {int((wrong & simple).sum())}, pair {int((wrong & pair).sum())}, "
           f"end {int((wrong & end).sum())}, faint {int((wrong & faint).sum())}]; "
           f"simple roots unresolved: {by_group(unres_simple)}; "
           f"hits without a root: {by_group(false_none)}; "
           f"tangent rays off the allowance: {by_group(tangent_bad)}")
    if wrong.any():
        i = int(np.flatnonzero(wrong)[0])
        msg += (f"; e.g. ray {i}: o {o32[i].tolist()}, d {d32[i].tolist()}, first root "
                f"{r[i]!r}, hit {bool(hit[i])}, t64 {t64[i]!r}")
    assert not (wrong.any() or unres_simple.any() or false_none.any() or tangent_bad.any()), msg
    return counts


def sphere_roots(o, d, centre, radius):
    """Both roots of |o + t d - centre| = radius in closed form, (n, 2)
    complex (a conjugate pair where the ray passes outside), from the point
    of closest approach (no cancellation for grazing rays)."""
    o, d = np.asarray(o, np.float64), np.asarray(d, np.float64)
    A = (d * d).sum(1)
    oc = o - np.asarray(centre, np.float64)
    tc = -(oc * d).sum(1) / A
    P = oc + tc[:, None] * d
    p = np.sqrt((P * P).sum(1))
    q = (p - radius) * (p + radius)              # |P|^2 - R^2
    h = np.sqrt(np.abs(q) / A)
    h = np.where(q <= 0, h + 0j, 1j * h)
    return np.stack([tc - h, tc + h], 1)


def assert_inside(name, lo, hi, values):
    """Every value (NaN excepted: undefined points) within [lo, hi]
    (broadcast against the values), no tolerance: the oracle of the
    enclosure tests (test_02, test_06)."""
    lo, hi = np.broadcast_to(lo, values.shape), np.broadcast_to(hi, values.shape)
    ok = np.isnan(values) | ((lo <= values) & (values <= hi))
    bad = np.argwhere(~ok)
    assert bad.size == 0, (f"{name}: {len(bad)} samples outside; first: value "
                           f"{values[tuple(bad[0])]} not in [{lo[tuple(bad[0])]}, {hi[tuple(bad[0])]}]")
