"""Attacks on lgshape's ray-search guarantees, each against a float64 oracle.

Every class builds a surface and rays meant to break a guarantee of the
contract (README "What counts as a surface", :mod:`lgshape.trace`) on one of
the three search paths: the *table path* (many primitives from
:mod:`lgshape.primitives`, or a written-out n-ary min / sum that
:func:`lgshape.tables.find_tables` turns into a table), the *polynomial
path* (f a polynomial of degree 3 to 8: each ray's polynomial) and the
*sinusoid path* (f a sum of products of sines and cosines of affine
functions). Positions far from the origin, whole scenes scaled by 1e-3 and
1e3, tiny parts next to big ones, near-touching parts, grazing rays, rays
from inside and on the surface, t windows (t_min, t_max), and rays through
the singular points of the distances (``table_singular_*``: along and
across a torus's axis and core circle, a capsule's segment, a box's centre
lines, centre planes and inner edges, a sphere's centre; in unions, smooth
unions and blends, written with the builders or as text, in normal boxes
and in flat ones; ``table_singular_issue`` holds the ray of a reported miss
down a torus's axis in a blend).

Oracles (float64, from the very float32 rays the kernel gets):

- unions: each primitive's ray interval in closed form (sphere: the
  quadratic from the closest approach; capsule: ray / finite cylinder and
  the two end balls; sharp box: the slab method; rounded box: the union of
  3 slabs, 12 edge cylinders and 8 corner balls; torus: the quartic's roots,
  companion-matrix eigenvalues polished by Newton), merged into the union's
  boundary points;
- smooth unions and blends: a float64 scan of f (evaluated over every row,
  :func:`lgshape.tables.evaluate_points` or the parsed text) over the part of
  the ray where roots can be (a smooth union of exact distances is at least
  min_i d_i - k, so it has roots only within k of a part; a blend is the
  threshold outside every kernel's support), sign changes bisected;
- polynomials: :func:`lgshape.reference.polynomial_roots` (companion
  matrices); sinusoids: a fine float64 scan.

:func:`judge` holds a trace against the oracle's roots with the contract's
allowances: the first root is *verified* when F changes sign across it
(float64, above the noise) with no other root or segment end within 2e-6
of the diagonal (twice the smallest interval); such a root must be hit to
1e-6 of the diagonal. Otherwise (a tangent touch, a sliver thinner than
the smallest interval, a root at t_min) the ray is *ambiguous*: a hit must
lie at a root up to the first verified one, and a miss is allowed only
where no verified root exists. Counted per class: rays, wrong (any
violation), capped (at the iteration bound), false hits (a hit with no
root there, or in front of the first root), misses (no hit, or one beyond
the first root), ambiguous rays, and the worst verified hit's distance to
the surface |f| / |grad f| at t64 (in diagonals).

Run: python -m lgshape.bench.attack [--rays 600] [--seed 1]
[--only CLASS ...] [--list]
"""
from __future__ import annotations

import argparse
import math
import sys
import time
import warnings
from dataclasses import dataclass, field

import numpy as np

import lgshape
import lgshape.primitives as P
from lgshape import tables
from lgshape.expr import evaluate, gradient, parse
from lgshape.reference import (along, bisect_sign_change, clip_to_box, polynomial_roots,
                               rod_intervals)

REL_TOL = 1e-6          # the contract's refinement tolerance, x diagonal
REL_H_MIN = 2e-6        # twice the smallest interval (1e-6 x diagonal)
REL_DELTA = 1e-4        # the neighbourhood of a root's sign check, x diagonal


def f32(v):
    """float64 values of v rounded to float32 (the builders' storage)."""
    return np.asarray(v, np.float64).astype(np.float32).astype(np.float64)


def unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def perpendicular(n, rng):
    return unit(np.cross(n, rng.normal(size=n.shape)))


# ---------------------------------------------------------------------------
# Scenes: primitives as their stored (float32) values
# ---------------------------------------------------------------------------

@dataclass
class Scene:
    """Primitives by kind, each row as the builders store it (float32
    values): sphere (c, r); capsule (a, ba, inv, r) with the effective end
    b = a + ba; box (c, e, rr): the box c +- (e + rr), edges rounded by rr
    (rr = 0: sharp); torus (c, R, r). ``radius`` scales each part's radius
    argument for a blend (its radius of influence)."""
    sphere: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    capsule: np.ndarray = field(default_factory=lambda: np.zeros((0, 8)))
    box: np.ndarray = field(default_factory=lambda: np.zeros((0, 7)))
    torus: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))

    @staticmethod
    def make(spheres=(), capsules=(), boxes=(), tori=()):
        """From float64 inputs: spheres (c, r), capsules (a, b, r), boxes
        (c, h, rounding), tori (c, R, r), rounded as the builders do."""
        s = Scene()
        if len(spheres):
            s.sphere = f32(np.asarray(spheres, np.float64).reshape(-1, 4))
        if len(capsules):
            c = np.asarray(capsules, np.float64).reshape(-1, 7)
            ba = c[:, 3:6] - c[:, :3]
            L2 = (ba ** 2).sum(1)
            inv = np.where(L2 > 0, 1.0 / np.where(L2 > 0, L2, 1.0), 0.0)   # a point: 0, as the builder
            s.capsule = np.column_stack([f32(c[:, :3]), f32(ba), f32(inv), f32(c[:, 6])])
        if len(boxes):
            b = np.asarray(boxes, np.float64).reshape(-1, 7)
            s.box = np.column_stack([f32(b[:, :3]), f32(b[:, 3:6] - b[:, 6:7]), f32(b[:, 6])])
        if len(tori):
            s.torus = f32(np.asarray(tori, np.float64).reshape(-1, 5))
        return s

    def parts(self):
        """The builders' parts (their float32 rounding of these float32
        values is exact: the same f)."""
        out = []
        if len(self.sphere):
            out.append(P.spheres(self.sphere[:, :3], self.sphere[:, 3]))
        if len(self.capsule):
            a = self.capsule[:, :3]
            out.append(P.capsules(a, a + self.capsule[:, 3:6], self.capsule[:, 7]))
        if len(self.box):
            e, rr = self.box[:, 3:6], self.box[:, 6]
            out.append(P.boxes(self.box[:, :3], e + rr[:, None], rr))
        if len(self.torus):
            out.append(P.tori(self.torus[:, :3], self.torus[:, 3], self.torus[:, 4]))
        return out

    def table(self, combine, **kw):
        return P.COMBINE[combine](*self.parts(), **kw)

    def count(self):
        return len(self.sphere) + len(self.capsule) + len(self.box) + len(self.torus)

    def check_parts(self):
        """The builders' stored values equal ours (so the oracle sees the
        kernel's f): the capsules' b - a and 1 / |b - a|^2 aside, which
        they recompute from a and b."""
        for part in self.parts():
            if part.kind == "box":
                e = f32(part.rows[:, 3:6] - part.rows[:, 6:7])
                assert np.array_equal(e, self.box[:, 3:6]), "box inner extents not exact"

    def transformed(self, scale=1.0, shift=(0.0, 0.0, 0.0)):
        """The scene scaled about the origin, then moved (float32 again)."""
        sh = np.asarray(shift, np.float64)
        s = Scene()
        if len(self.sphere):
            s.sphere = f32(np.column_stack([self.sphere[:, :3] * scale + sh, self.sphere[:, 3] * scale]))
        if len(self.capsule):
            a = self.capsule[:, :3] * scale + sh
            b = (self.capsule[:, :3] + self.capsule[:, 3:6]) * scale + sh
            s = _merge(s, Scene.make(capsules=np.column_stack([a, b, self.capsule[:, 7] * scale])))
        if len(self.box):
            s = _merge(s, Scene.make(boxes=np.column_stack([
                self.box[:, :3] * scale + sh, (self.box[:, 3:6] + self.box[:, 6:7]) * scale,
                self.box[:, 6] * scale])))
        if len(self.torus):
            s.torus = f32(np.column_stack([self.torus[:, :3] * scale + sh, self.torus[:, 3:] * scale]))
        return s


def _merge(a: Scene, b: Scene) -> Scene:
    return Scene(*(np.concatenate([getattr(a, k), getattr(b, k)]) if len(getattr(b, k))
                   else getattr(a, k) for k in ("sphere", "capsule", "box", "torus")))


def random_scene(rng, centre=(0.0, 0.0, 0.0), n=16, size=1.0, blend=False, sharp=True):
    """n of each kind in the cube centre +- size: spheres, capsules, rounded
    boxes, sharp boxes (``sharp``) and tori; radii as fractions of size
    (larger for a blend: its parts' radii of influence)."""
    c = np.asarray(centre, np.float64)
    s = size
    g = 2.0 if blend else 1.0

    def at(k):
        return c + s * rng.uniform(-0.85, 0.85, (k, 3))
    sph = np.column_stack([at(n), g * s * rng.uniform(0.05, 0.15, n)])
    a = at(n)
    b = a + s * unit(rng.normal(size=(n, 3))) * rng.uniform(0.1, 0.4, (n, 1))
    cap = np.column_stack([a, b, g * s * rng.uniform(0.03, 0.08, n)])
    h = s * rng.uniform(0.04, 0.15, (n, 3))
    rr = h.min(1) * rng.uniform(0.2, 0.9, n)
    if blend:
        h, rr = 1.5 * h, 1.5 * h.min(1) * rng.uniform(0.6, 0.95, n)
    box = [np.column_stack([at(n), h, rr])]
    if sharp and not blend:
        box.append(np.column_stack([at(n), s * rng.uniform(0.04, 0.15, (n, 3)), np.zeros(n)]))
    R = s * rng.uniform(0.1, 0.2, n)
    tor = np.column_stack([at(n), R, R * rng.uniform(0.15, 0.35 if not blend else 0.6, n)])
    return Scene.make(sph, cap, np.concatenate(box), tor)


# ---------------------------------------------------------------------------
# The same primitives written out as text (find_tables makes tables of them)
# ---------------------------------------------------------------------------

def _r(v):
    return repr(float(v))


def _off(axis, v):
    return f"({axis} - {_r(v)})"


def _seg_h(row):
    a, ba, inv = row[:3], row[3:6], row[6]
    dot = " + ".join(f"{_off(ax, a[i])}*{_r(ba[i])}" for i, ax in enumerate("xyz"))
    return f"min(max(({dot})*{_r(inv)}, 0), 1)"


def _seg_d2(row):
    a, ba = row[:3], row[3:6]
    h = _seg_h(row)
    return " + ".join(f"({_off(ax, a[i])} - {_r(ba[i])}*{h})^2" for i, ax in enumerate("xyz"))


def _box_q(row):
    return [f"abs({_off(ax, row[i])}) - {_r(row[3 + i])}" for i, ax in enumerate("xyz")]


def distance_texts(scene: Scene):
    """Per primitive, its signed distance as text (the builders' formulas):
    one structure per kind (rounded and sharp boxes apart)."""
    out = []
    for r in scene.sphere:
        out.append(f"sqrt({_off('x', r[0])}^2 + {_off('y', r[1])}^2 + {_off('z', r[2])}^2) - {_r(r[3])}")
    for r in scene.capsule:
        out.append(f"sqrt({_seg_d2(r)}) - {_r(r[7])}")
    for r in scene.box:
        q = _box_q(r)
        if r[6] > 0:
            outside = " + ".join(f"max({v}, 0)^2" for v in q)
            out.append(f"sqrt({outside}) + min(max({', '.join(q)}), 0) - {_r(r[6])}")
        else:
            out.append(f"max({', '.join(q)})")
    for r in scene.torus:
        out.append(f"sqrt((sqrt({_off('x', r[0])}^2 + {_off('y', r[1])}^2) - {_r(r[3])})^2 + "
                   f"{_off('z', r[2])}^2) - {_r(r[4])}")
    return out


def kernel_texts(scene: Scene):
    """Per primitive, its blend kernel K = max(1 - d^2 / R^2, 0)^3 of the
    skeleton distance d as text (R: the radius argument)."""
    out = []
    for r in scene.sphere:
        d2 = f"{_off('x', r[0])}^2 + {_off('y', r[1])}^2 + {_off('z', r[2])}^2"
        out.append(f"max(1 - ({d2})/{_r(r[3] ** 2)}, 0)^3")
    for r in scene.capsule:
        out.append(f"max(1 - ({_seg_d2(r)})/{_r(r[7] ** 2)}, 0)^3")
    for r in scene.box:
        d2 = " + ".join(f"max({v}, 0)^2" for v in _box_q(r))
        out.append(f"max(1 - ({d2})/{_r(r[6] ** 2)}, 0)^3")
    for r in scene.torus:
        d2 = f"(sqrt({_off('x', r[0])}^2 + {_off('y', r[1])}^2) - {_r(r[3])})^2 + {_off('z', r[2])}^2"
        out.append(f"max(1 - ({d2})/{_r(r[4] ** 2)}, 0)^3")
    return out


def union_text(scene):
    return "min(" + ", ".join(distance_texts(scene)) + ")"


def blend_text(scene, threshold):
    return _r(threshold) + "".join(" - " + k for k in kernel_texts(scene))


# ---------------------------------------------------------------------------
# Closed-form ray intervals of the primitives (n rays x m primitives)
# ---------------------------------------------------------------------------

def ball_intervals(o, d, c, r):
    """Entry and exit of the balls |p - c_j| <= r_j (n, m), NaN where the
    line misses; from the closest approach (no cancellation far away)."""
    oc = o[:, None, :] - c[None]
    A = (d * d).sum(1)[:, None]
    tc = -(oc * d[:, None, :]).sum(-1) / A
    m = oc + tc[..., None] * d[:, None, :]
    q = (r[None] - np.sqrt((m * m).sum(-1))) * (r[None] + np.sqrt((m * m).sum(-1)))
    with np.errstate(invalid="ignore"):
        h = np.sqrt(q / A)
    ok = q >= 0
    return np.where(ok, tc - h, np.nan), np.where(ok, tc + h, np.nan)


def slab_intervals(o, d, lo, hi):
    """Entry and exit of the boxes [lo_j, hi_j] (n, m), NaN where missed."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d[:, None, :]
        ta = (lo[None] - o[:, None, :]) * inv
        tb = (hi[None] - o[:, None, :]) * inv
        zero = d[:, None, :] == 0
        inside = (o[:, None, :] >= lo[None]) & (o[:, None, :] <= hi[None])
        tn = np.where(zero, np.where(inside, -np.inf, np.inf), np.minimum(ta, tb)).max(-1)
        tf = np.where(zero, np.where(inside, np.inf, -np.inf), np.maximum(ta, tb)).min(-1)
    ok = tn <= tf
    return np.where(ok, tn, np.nan), np.where(ok, tf, np.nan)


def hull(pieces):
    """The hull of several (tn, tf) pieces of one convex solid."""
    tn = np.stack([p[0] for p in pieces], -1)
    tf = np.stack([p[1] for p in pieces], -1)
    with np.errstate(invalid="ignore"):
        a = np.where(np.isnan(tn), np.inf, tn).min(-1)
        b = np.where(np.isnan(tf), -np.inf, tf).max(-1)
    ok = a <= b
    return np.where(ok, a, np.nan), np.where(ok, b, np.nan)


def capsule_intervals(o, d, rows, grow=0.0):
    a = rows[:, :3]
    b = a + rows[:, 3:6]
    r = rows[:, 7] + grow
    return hull([rod_intervals(o, d, a, b, r), ball_intervals(o, d, a, r),
                 ball_intervals(o, d, b, r)])


def box_intervals(o, d, rows, grow=0.0):
    """Boxes c +- (e + rr), edges rounded by rr (the union of 3 slabs, 12
    edge cylinders and 8 corner balls; a slab alone where rr = 0);
    ``grow`` inflates the rounding (the solid within ``grow`` of the box)."""
    c, e, rr = rows[:, :3], rows[:, 3:6], rows[:, 6] + grow
    pieces = []
    for i in range(3):
        g = e.copy()
        g[:, i] += rr
        pieces.append(slab_intervals(o, d, c - g, c + g))
    sharp = rr <= 0
    if not sharp.all():
        r = np.where(sharp, 0.0, rr)
        for i in range(3):
            j, k = [q for q in range(3) if q != i]
            for sj in (-1, 1):
                for sk in (-1, 1):
                    a, b = c.copy(), c.copy()
                    a[:, i] -= e[:, i]
                    b[:, i] += e[:, i]
                    for p in (a, b):
                        p[:, j] += sj * e[:, j]
                        p[:, k] += sk * e[:, k]
                    tn, tf = rod_intervals(o, d, a, b, np.where(sharp, 1.0, r))
                    pieces.append((np.where(sharp[None], np.nan, tn), np.where(sharp[None], np.nan, tf)))
        for s in np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).T.reshape(-1, 3):
            tn, tf = ball_intervals(o, d, c + s * e, np.where(sharp, 1.0, r))
            pieces.append((np.where(sharp[None], np.nan, tn), np.where(sharp[None], np.nan, tf)))
    return hull(pieces)


def torus_roots(o, d, rows, grow=0.0):
    """The quartic's real roots per (ray, torus), (n, m, 4) sorted, NaN
    padded: companion-matrix eigenvalues in float64 (about the ray's closest
    approach to the centre), the real ones (|Im| < 1e-6 (R + r)) polished
    by Newton on the quartic."""
    c, R, r = rows[:, :3], rows[:, 3], rows[:, 4] + grow
    q = o[:, None, :] - c[None]
    A = (d * d).sum(1)[:, None]
    tc = -(q * d[:, None, :]).sum(-1) / A
    q = q + tc[..., None] * d[:, None, :]
    dd = np.broadcast_to(d[:, None, :], q.shape)
    B = (q * dd).sum(-1)
    C = (q * q).sum(-1)
    Axy = (dd[..., :2] ** 2).sum(-1)
    Bxy = (q[..., :2] * dd[..., :2]).sum(-1)
    Cxy = (q[..., :2] ** 2).sum(-1)
    K = (R * R - r * r)[None]
    R2 = (R * R)[None]
    A = np.broadcast_to(A, C.shape)
    co = np.stack([A * A, 4 * A * B, 4 * B * B + 2 * A * (C + K) - 4 * R2 * Axy,
                   4 * B * (C + K) - 8 * R2 * Bxy, (C + K) ** 2 - 4 * R2 * Cxy], -1)
    near = C <= ((R + r) ** 2)[None] * 1.0001
    out = np.full(C.shape + (4,), np.nan)
    idx = np.nonzero(near)
    if len(idx[0]):
        cf = co[idx]
        comp = np.zeros((len(cf), 4, 4))
        comp[:, 1:, :-1] = np.eye(3)
        comp[:, :, -1] = -cf[:, [4, 3, 2, 1]] / cf[:, :1]
        s = np.linalg.eigvals(comp)
        scale = (R + r)[idx[1]][:, None]
        real = np.abs(s.imag) < 1e-6 * scale
        x = s.real.copy()
        for _ in range(3):
            p = ((((cf[:, 0:1] * x + cf[:, 1:2]) * x + cf[:, 2:3]) * x + cf[:, 3:4]) * x + cf[:, 4:5])
            dp = (((4 * cf[:, 0:1] * x + 3 * cf[:, 1:2]) * x + 2 * cf[:, 2:3]) * x + cf[:, 3:4])
            with np.errstate(divide="ignore", invalid="ignore"):
                step = np.where(dp != 0, p / dp, 0.0)
            ok = np.abs(step) < 1e-6 * scale
            x = np.where(ok, x - step, x)
        x = np.sort(np.where(real, x, np.nan), 1)
        out[idx] = x + tc[idx][:, None]
    return out


def torus_intervals(o, d, rows, grow=0.0):
    """Up to two (entry, exit) intervals per (ray, torus): ((n, m), (n, m))
    twice; a lone or triple real root (a numerically borderline touch) is
    taken as zero-length touches."""
    t = torus_roots(o, d, rows, grow)
    cnt = np.isfinite(t).sum(-1)
    even = cnt % 2 == 0
    i1 = (np.where(even, t[..., 0], t[..., 0]), np.where(even, t[..., 1], t[..., 0]))
    i2 = (np.where(even, t[..., 2], np.where(cnt == 3, t[..., 1], np.nan)),
          np.where(even, t[..., 3], np.where(cnt == 3, t[..., 1], np.nan)))
    i3 = (np.where(cnt == 3, t[..., 2], np.nan), np.where(cnt == 3, t[..., 2], np.nan))
    return [i1, i2, i3]


def scene_intervals(scene: Scene, o, d, grow=0.0):
    """Every (tn, tf) interval of every primitive's solid along the rays,
    grown by ``grow`` (the points within ``grow`` of it). A blend kernel's
    support is the solid of its part's row (the skeleton's neighbourhood
    of the radius argument: a box's is the box itself)."""
    out = []
    if len(scene.sphere):
        out.append(ball_intervals(o, d, scene.sphere[:, :3], scene.sphere[:, 3] + grow))
    if len(scene.capsule):
        out.append(capsule_intervals(o, d, scene.capsule, grow))
    if len(scene.box):
        out.append(box_intervals(o, d, scene.box, grow))
    if len(scene.torus):
        out += torus_intervals(o, d, scene.torus, grow)
    return out


def union_roots(intervals, t0, t1):
    """The boundary points of the union of the intervals inside (t0, t1):
    (n, K) sorted, NaN padded (the roots of min_j d_j along each ray)."""
    tn = np.concatenate([i[0] for i in intervals], 1)
    tf = np.concatenate([i[1] for i in intervals], 1)
    valid = np.isfinite(tn) & np.isfinite(tf) & (tf >= tn)
    a, b = t0[:, None], t1[:, None]
    start = (valid & (tn <= a) & (tf > a)).sum(1)
    enter = valid & (tn > a) & (tn < b)
    leave = valid & (tf > a) & (tf < b)
    ev = np.concatenate([np.where(enter, tn, np.inf), np.where(leave, tf, np.inf)], 1)
    mk = np.concatenate([np.where(enter, 1, 0), np.where(leave, -1, 0)], 1)
    # at equal times, entries first (a zero-length touch stays a touch)
    order = np.lexsort((-mk, ev), axis=1)
    ev, mk = np.take_along_axis(ev, order, 1), np.take_along_axis(mk, order, 1)
    cum = start[:, None] + np.cumsum(mk, 1)
    before = cum - mk
    root = np.isfinite(ev) & (mk != 0) & ((before == 0) != (cum == 0))
    r = np.sort(np.where(root, ev, np.inf), 1)
    k = max(1, int(root.sum(1).max(initial=0)))
    r = r[:, :k]
    return np.where(np.isfinite(r), r, np.nan)


def scan_roots(F, o, d, ta, tb, steps=1024, max_roots=8, bisections=52):
    """Sign changes of F on [ta, tb] from ``steps`` samples, each bisected
    (n, max_roots) sorted, NaN padded; rays with ta >= tb have none. A
    sample exactly 0 counts as a root there."""
    n = len(o)
    ok = np.isfinite(ta) & np.isfinite(tb) & (tb > ta)
    s = np.linspace(0.0, 1.0, steps + 1)
    out = np.full((n, max_roots), np.nan)
    chunk = max(1, 2 ** 18 // (steps + 1))
    ray, a, b, fa = [], [], [], []
    for k0 in range(0, n, chunk):
        i = np.flatnonzero(ok[k0:k0 + chunk]) + k0
        if not len(i):
            continue
        t = ta[i, None] + (tb - ta)[i, None] * s[None]
        v = along(F, o[i], d[i], t)
        sg = np.sign(v)
        ch = (sg[:, :-1] * sg[:, 1:] < 0) | ((sg[:, :-1] != 0) & (sg[:, 1:] == 0))
        rank = np.cumsum(ch, 1) - 1
        ch &= rank < max_roots
        r, c = np.nonzero(ch)
        ray.append(i[r])
        a.append(t[r, c])
        b.append(t[r, c + 1])
        fa.append(v[r, c])
    if not ray:
        return out
    ray, a, b, fa = (np.concatenate(q) for q in (ray, a, b, fa))
    a, b = bisect_sign_change(F, o[ray], d[ray], a, b, fa, bisections)
    root = 0.5 * (a + b)
    # scatter into (n, max_roots): position = rank within its ray
    order = np.lexsort((root, ray))
    ray, root = ray[order], root[order]
    first = np.searchsorted(ray, ray)
    out[ray, np.arange(len(ray)) - first] = root
    return out


# ---------------------------------------------------------------------------
# f in float64 (the oracle's view), its gradient, and the judge
# ---------------------------------------------------------------------------

class Fn:
    """f as a float64 callable F(X, Y, Z): a TableForm over every row
    (:func:`lgshape.tables.evaluate_points`, without building the whole
    expression) or an expression; |grad f| by central differences (no
    symbolic gradient of a large expression to keep alive)."""

    def __init__(self, f):
        self.tf = f if isinstance(f, tables.TableForm) else None
        self.expr = None if self.tf is not None else f

    def __call__(self, X, Y, Z):
        shape = np.broadcast(X, Y, Z).shape
        p = np.stack([np.broadcast_to(v, shape).reshape(-1) for v in (X, Y, Z)], 1)
        with np.errstate(all="ignore"):
            if self.tf is not None:
                v = tables.evaluate_points(self.tf, p)
            else:
                v = np.broadcast_to(evaluate(self.expr, dict(zip("xyz", p.T))), len(p))
        return np.asarray(v, np.float64).reshape(shape)

    def distance(self, p, h):
        """|f| / |grad f| at points p (n, 3), float64, the gradient by
        central differences of step h."""
        p = np.asarray(p, np.float64)
        g = np.zeros_like(p)
        for i in range(3):
            e = np.zeros(3)
            e[i] = h
            g[:, i] = (self(*(p + e).T) - self(*(p - e).T)) / (2 * h)
        with np.errstate(all="ignore"):
            return np.abs(self(*p.T)) / np.linalg.norm(g, axis=1)


@dataclass
class Verdict:
    rays: int
    wrong: int
    capped: int
    false_hits: int
    misses: int
    ambiguous: int
    verified: int
    hidden: int          # hits at an F-verified root the (scan) oracle did not list
    touches: int         # hits where F is 0 to float64 noise (allowed: tangent touches)
    max_dist: float      # worst |f| / |grad f| at t64 of verified hits, in diagonals
    max_dist32: float    # the same at the float32 t, minus ulp(t) / 2 |d|, in diagonals
    iterations: float    # mean search + refinement iterations
    example: str = ""
    masks: dict = field(default_factory=dict, repr=False)

    def row(self):
        return (self.rays, self.wrong, self.capped, self.false_hits, self.misses, self.ambiguous)


def _local_root(F, o, d, t, w):
    """Whether F has a root within w of t (a sign change among 65 samples
    of [t - w, t + w], or a sample exactly 0)."""
    s = np.linspace(-1.0, 1.0, 65)
    v = along(F, o, d, t[:, None] + w[:, None] * s[None])
    sg = np.sign(v)
    return (sg == 0).any(1) | (sg[:, :-1] * sg[:, 1:] < 0).any(1)


def judge(res, F: Fn, o32, d32, roots, lo, hi, t_min=0.0, t_max=np.inf, complete=True,
          distance=True) -> Verdict:
    """A trace's answers against the oracle's roots (see the module text).
    ``roots`` (n, k): the oracle's real roots of F along each ray (NaN
    padded; any order); ``complete`` False for a scan, whose list may lack
    pairs closer than its step: a hit where F changes sign within 2 tol is
    then a root it did not list (``hidden``), not a false hit."""
    o, d = np.asarray(o32, np.float64), np.asarray(d32, np.float64)
    n = len(o)
    t64 = np.asarray(res.t64, np.float64)
    t32 = np.asarray(res.t, np.float64)
    hit = np.asarray(res.hit, bool)
    capped = np.asarray(res.capped, bool)
    iters = np.asarray(res.iterations, np.float64)
    diag = float(np.linalg.norm(np.asarray(hi) - np.asarray(lo)))
    dn = np.linalg.norm(d, axis=1)
    tol = REL_TOL * diag / dn
    h_min, delta = REL_H_MIN * diag / dn, REL_DELTA * diag / dn
    tmn = np.broadcast_to(np.asarray(t_min, np.float64), (n,))
    tmx = np.broadcast_to(np.asarray(t_max, np.float64), (n,))
    t0, t1 = clip_to_box(o, d, np.asarray(lo, np.float64), np.asarray(hi, np.float64))
    t0, t1 = np.maximum(t0, tmn), np.minimum(t1, tmx)
    seg = t1 >= t0
    with np.errstate(invalid="ignore"):
        roots = np.asarray(roots, np.float64).reshape(n, -1)
        roots = np.where((roots >= t0[:, None] - tol[:, None]) & (roots <= t1[:, None] + tol[:, None])
                         & seg[:, None], roots, np.nan)
    c = np.sort(roots, 1)
    has = np.isfinite(c)
    k = c.shape[1]
    # noise of F: float64 rounding at these magnitudes (positions, values)
    s9 = np.linspace(0, 1, 9)
    tt = np.where(seg, t0, 0)[:, None] + np.where(seg, np.minimum(t1 - t0, 1e30), 0)[:, None] * s9
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)      # all-NaN rows: no segment
        M = np.nanmax(np.abs(np.where(np.isfinite(tt), along(F, o, d, np.where(np.isfinite(tt), tt, 0)),
                                      0)), 1)
    noise = 1e-12 * (1 + np.nan_to_num(M))
    with np.errstate(invalid="ignore"):
        gp = np.diff(np.concatenate([np.full((n, 1), -np.inf), c], 1), axis=1)
        gn = np.diff(np.concatenate([c, np.full((n, 1), np.inf)], 1), axis=1)
        gp, gn = np.where(np.isnan(gp), np.inf, gp), np.where(np.isnan(gn), np.inf, gn)
        h = np.minimum.reduce([np.broadcast_to(delta[:, None], c.shape), gp / 2, gn / 2,
                               c - t0[:, None], t1[:, None] - c])
        h = np.where(has, h, 0.0)
        cs = np.where(has, c, 0.0)
        fm, fp = along(F, o, d, cs - h), along(F, o, d, cs + h)
        ver = has & (h >= h_min[:, None]) & (np.sign(fm) * np.sign(fp) < 0) & \
            (np.minimum(np.abs(fm), np.abs(fp)) > noise[:, None])
    none = ~has[:, 0]
    first = ver[:, 0]
    amb = has[:, 0] & ~first
    any_ver = ver.any(1)
    k_ver = np.where(any_ver, np.argmax(ver, 1), k - 1)
    upto = np.arange(k)[None] <= k_ver[:, None]
    with np.errstate(invalid="ignore"):
        near = has & upto & (np.abs(c - t64[:, None]) <= 1.001 * tol[:, None])
    at_root = hit & near.any(1)
    # a hit at a root the oracle did not list (F changes sign within 2 tol)
    chk = hit & ~at_root & np.isfinite(t64)
    real_root = np.zeros(n, bool)
    if chk.any():
        i = np.flatnonzero(chk)
        with np.errstate(all="ignore"):
            real_root[i] = _local_root(F, o[i], d[i], t64[i], 2 * tol[i])
    first_t = np.where(has[:, 0], c[:, 0], np.inf)
    ver_t = np.where(any_ver, c[np.arange(n), k_ver], np.inf)
    hidden = chk & real_root & (~complete) & (t64 < ver_t + tol)
    # a touch: F within float64 noise of 0 at the hit (a line in a face's
    # plane, along an edge, an origin on the surface): allowed up to the
    # first verified root
    touch = np.zeros(n, bool)
    if chk.any():
        i = np.flatnonzero(chk)
        with np.errstate(all="ignore"):
            touch[i] = np.abs(along(F, o[i], d[i], t64[i])) <= noise[i]
    touch &= t64 < ver_t + tol
    ok_hit = at_root | hidden | touch
    false = hit & ~ok_hit & (t64 < np.where(any_ver, ver_t, np.inf) - tol)
    false |= hit & ~ok_hit & ~any_ver
    miss = any_ver & (~hit | (~ok_hit & (t64 > ver_t + tol)))
    miss |= any_ver & hit & ~ok_hit & ~false
    wrong = capped | false | miss
    # distance to the surface at the verified hits
    dist, dist32 = 0.0, 0.0
    good = first & hit & at_root & ~capped
    if distance and good.any():
        i = np.flatnonzero(good)
        p = o[i] + t64[i, None] * d[i]
        dist = float(np.nanmax(F.distance(p, 2e-7 * diag)) / diag)
        p32 = o[i] + t32[i, None] * d[i]
        ulp = np.spacing(np.abs(t32[i]).astype(np.float32)).astype(np.float64) * 0.5 * dn[i]
        dist32 = float(np.nanmax(F.distance(p32, 2e-7 * diag) - ulp) / diag)
    ex = ""
    if wrong.any():
        j = int(np.flatnonzero(wrong)[0])
        ex = (f"ray {j}: o {o32[j].tolist()} d {d32[j].tolist()} roots {c[j][has[j]][:4].tolist()} "
              f"verified {ver[j][has[j]][:4].tolist()} hit {bool(hit[j])} t64 {t64[j]!r} "
              f"capped {bool(capped[j])} iterations {int(iters[j])}")
    return Verdict(n, int(wrong.sum()), int(capped.sum()), int(false.sum()), int(miss.sum()),
                   int(amb.sum()), int(first.sum()), int(hidden.sum()),
                   int((touch & ~at_root & ~hidden).sum()), dist, dist32,
                   float(iters.mean()) if n else 0.0, ex,
                   masks=dict(wrong=wrong, capped=capped, false=false, miss=miss, amb=amb,
                              first=first, none=none, first_t=first_t, ver_t=ver_t,
                              unlisted=chk & real_root & complete & ~touch, touch=touch))


# ---------------------------------------------------------------------------
# Rays
# ---------------------------------------------------------------------------

def camera_rays(rng, lo, hi, n, radius=2.5):
    """From a sphere of ``radius`` diagonals about the box centre, aimed at
    uniform points of the box (float32)."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    c = 0.5 * (lo + hi)
    o = c + radius * np.linalg.norm(hi - lo) * unit(rng.normal(size=(n, 3)))
    aim = lo + (hi - lo) * rng.uniform(0, 1, (n, 3))
    return np.float32(o), np.float32(unit(aim - o))


def inner_rays(rng, lo, hi, n):
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    o = lo + (hi - lo) * rng.uniform(0, 1, (n, 3))
    return np.float32(o), np.float32(unit(rng.normal(size=(n, 3))))


def surface_points(scene: Scene, rng, n):
    """n points on the primitives' surfaces with their outward unit normals
    (closed forms; points may lie inside other parts)."""
    kinds = [k for k in ("sphere", "capsule", "box", "torus") if len(getattr(scene, k))]
    which = rng.choice(len(kinds), n)
    P_, N_ = np.zeros((n, 3)), np.zeros((n, 3))
    for ki, kind in enumerate(kinds):
        sel = np.flatnonzero(which == ki)
        rows = getattr(scene, kind)
        rows = rows[rng.integers(0, len(rows), len(sel))]
        m = len(sel)
        if not m:
            continue
        if kind == "sphere":
            nr = unit(rng.normal(size=(m, 3)))
            p = rows[:, :3] + rows[:, 3:4] * nr
        elif kind == "capsule":
            a, ba, r = rows[:, :3], rows[:, 3:6], rows[:, 7:8]
            u = unit(np.where((np.abs(ba).sum(1) > 0)[:, None], ba, rng.normal(size=ba.shape)))
            side = rng.uniform(0, 1, m) < 0.6
            nr = np.where(side[:, None], perpendicular(u, rng), unit(rng.normal(size=(m, 3))))
            s = np.where(side, rng.uniform(0, 1, m), np.where((nr * u).sum(1) > 0, 1.0, 0.0))
            p = a + s[:, None] * ba + r * nr
        elif kind == "box":
            c, e, rr = rows[:, :3], rows[:, 3:6], rows[:, 6:7]
            # a face (flat part), an edge or a corner of the rounded box
            part = rng.integers(0, 3, m)
            nr = np.zeros((m, 3))
            axis = rng.integers(0, 3, m)
            sg = rng.choice([-1.0, 1.0], (m, 3))
            q = rng.uniform(-1, 1, (m, 3)) * e
            face = part == 0
            nr[np.flatnonzero(face), axis[face]] = sg[face, axis[face]]
            edge = part == 1
            # edges: along `axis`, at signed corners of the two others
            ang = rng.uniform(0, np.pi / 2, m)
            for i in np.flatnonzero(edge):
                j, k = [a_ for a_ in range(3) if a_ != axis[i]]
                q[i, j], q[i, k] = sg[i, j] * e[i, j], sg[i, k] * e[i, k]
                nr[i, j], nr[i, k] = sg[i, j] * math.cos(ang[i]), sg[i, k] * math.sin(ang[i])
            corner = part == 2
            q[corner] = sg[corner] * e[corner]
            nr[corner] = sg[corner] * unit(np.abs(rng.normal(size=(int(corner.sum()), 3))))
            q[np.flatnonzero(face), axis[face]] = sg[face, axis[face]] * e[face, axis[face]]
            # (on a sharp box's edge or corner, nr is a supporting plane's normal)
            p = c + q + rr * nr
        else:
            c, R, r = rows[:, :3], rows[:, 3:4], rows[:, 4:5]
            u, v = rng.uniform(0, 2 * np.pi, (2, m))
            ring = np.stack([np.cos(u), np.sin(u), np.zeros(m)], 1)
            nr = np.cos(v)[:, None] * ring + np.sin(v)[:, None] * np.array([0.0, 0.0, 1.0])
            p = c + R * ring + r * nr
        P_[sel], N_[sel] = p, nr
    return P_, N_


def grazing_rays(rng, p, nrm, offsets, back, aimed=False):
    """Rays along random tangents at p, moved off by each offset (absolute)
    outward and inward, starting ``back`` before the touching point. The
    tangent is kept as it is (on a box's face: a direction with a zero
    component), or with ``aimed`` the float32 origin is taken first and the
    direction aimed from it at the offset point (far from the origin, where
    float32 origins are coarse, only this keeps the offset)."""
    t = perpendicular(nrm, rng)
    o, d = [], []
    for off in offsets:
        for s in (1.0, -1.0):
            q = p + s * off * nrm
            if aimed:
                oo = f32(q - back * t)
                o.append(oo)
                d.append(unit(q - oo))
            else:
                o.append(q - back * t)
                d.append(t)
    return np.float32(np.concatenate(o)), np.float32(np.concatenate(d))


# ---------------------------------------------------------------------------
# Oracles of whole cases
# ---------------------------------------------------------------------------


def union_oracle(scene, o32, d32, lo, hi, t_min=0.0):
    """The union's roots along each ray in the box beyond t_min (from the
    primitives' closed-form intervals)."""
    o, d = o32.astype(np.float64), d32.astype(np.float64)
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    t0, t1 = clip_to_box(o, d, lo, hi, t_min)
    # from a little before t0: a root just before t_min is listed (the judge
    # keeps those within the tolerance: an ambiguous root at the start)
    pad = REL_H_MIN * float(np.linalg.norm(hi - lo)) / np.linalg.norm(d, axis=1)
    return union_roots(scene_intervals(scene, o, d), t0 - pad, np.maximum(t1, t0))


def scan_oracle(F, scene, o32, d32, lo, hi, grow, steps=1024, t_min=0.0):
    """The scan over the hull of the parts grown by ``grow`` along each ray
    (where the roots can be: see the module text), beyond t_min."""
    o, d = o32.astype(np.float64), d32.astype(np.float64)
    t0, t1 = clip_to_box(o, d, np.asarray(lo, np.float64), np.asarray(hi, np.float64), t_min)
    iv = scene_intervals(scene, o, d, grow=grow)
    tn = np.concatenate([i[0] for i in iv], 1)
    tf = np.concatenate([i[1] for i in iv], 1)
    with np.errstate(invalid="ignore"):
        a = np.where(np.isnan(tn), np.inf, tn).min(1)
        b = np.where(np.isnan(tf), -np.inf, tf).max(1)
    ta, tb = np.maximum(a, t0), np.minimum(b, t1)
    return scan_roots(F, o, d, ta, tb, steps=steps)


def poly_oracle(F, degree, o32, d32, lo, hi, t_min=0.0):
    """All real roots of a polynomial F along each ray in the box (float64
    companion-matrix eigenvalues; |Im| <= 1e-6 diag counts as real)."""
    o, d = o32.astype(np.float64), d32.astype(np.float64)
    t0, t1 = clip_to_box(o, d, np.asarray(lo, np.float64), np.asarray(hi, np.float64), t_min)
    rts = polynomial_roots(F, degree, o, d, t0, np.where(t1 > t0, t1, t0 + 1.0))
    diag = float(np.linalg.norm(np.asarray(hi) - np.asarray(lo)))
    ok = (np.abs(rts.imag) <= 1e-6 * diag) & (t1 > t0)[:, None]
    return np.where(ok, rts.real, np.nan)


def sweep_oracle(F, o32, d32, lo, hi, steps, t_min=0.0, max_roots=8):
    """A scan of F over the whole segment in the box (no closed form)."""
    o, d = o32.astype(np.float64), d32.astype(np.float64)
    t0, t1 = clip_to_box(o, d, np.asarray(lo, np.float64), np.asarray(hi, np.float64), t_min)
    return scan_roots(F, o, d, t0, t1, steps=steps, max_roots=max_roots)


# ---------------------------------------------------------------------------
# Ray groups on, inside and grazing a scene
# ---------------------------------------------------------------------------

def inside_points(scene: Scene, rng, n):
    """n points strictly inside the primitives (half way in)."""
    kinds = [k for k in ("sphere", "capsule", "box", "torus") if len(getattr(scene, k))]
    which = rng.choice(len(kinds), n)
    out = np.zeros((n, 3))
    for ki, kind in enumerate(kinds):
        sel = np.flatnonzero(which == ki)
        m = len(sel)
        if not m:
            continue
        rows = getattr(scene, kind)
        rows = rows[rng.integers(0, len(rows), m)]
        u = unit(rng.normal(size=(m, 3))) * rng.uniform(0, 0.5, (m, 1))
        if kind == "sphere":
            p = rows[:, :3] + rows[:, 3:4] * u
        elif kind == "capsule":
            p = rows[:, :3] + rng.uniform(0, 1, (m, 1)) * rows[:, 3:6] + rows[:, 7:8] * u
        elif kind == "box":
            p = rows[:, :3] + rng.uniform(-0.5, 0.5, (m, 3)) * (rows[:, 3:6] + rows[:, 6:7])
        else:
            a = rng.uniform(0, 2 * np.pi, m)
            ring = np.stack([np.cos(a), np.sin(a), np.zeros(m)], 1)
            p = rows[:, :3] + rows[:, 3:4] * ring + rows[:, 4:5] * u
        out[sel] = p
    return out


def scene_rays(scene: Scene, rng, lo, hi, n, groups=("camera", "grazing", "aimed", "inside",
                                                      "surface")):
    """Ray groups {name: (o32, d32, t_min per ray)}, about n rays in all:
    camera rays; grazing rays at surface points (random tangents moved off
    by 1e-7 .. 1e-2 diagonals outward and inward; ``grazing`` keeps the
    tangent exactly, ``aimed`` aims from the rounded origin); rays from
    inside parts in random directions; rays from surface points (rounded to
    float32) inward, outward, tangent and random, with t_min 0 and 1e-3
    diagonals."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    diag = float(np.linalg.norm(hi - lo))
    offsets = diag * 10.0 ** np.arange(-7.0, -1.0)
    per = max(1, n // len(groups))
    out = {}
    for g in groups:
        if g == "camera":
            o, d = camera_rays(rng, lo, hi, per)
            t = np.zeros(len(o))
        elif g in ("grazing", "aimed"):
            p, nr = surface_points(scene, rng, max(1, per // (2 * len(offsets))))
            o, d = grazing_rays(rng, p, nr, offsets, 0.3 * diag, aimed=g == "aimed")
            t = np.zeros(len(o))
        elif g == "inside":
            o = np.float32(inside_points(scene, rng, per))
            d = np.float32(unit(rng.normal(size=(per, 3))))
            t = np.zeros(per)
        else:
            m = max(1, per // 8)
            p, nr = surface_points(scene, rng, m)
            dirs = [-nr, nr, perpendicular(nr, rng), unit(rng.normal(size=nr.shape))]
            o = np.float32(np.tile(p, (8, 1)))
            d = np.float32(np.concatenate(dirs * 2))
            t = np.concatenate([np.zeros(4 * m), np.full(4 * m, 1e-3 * diag)])
        out[g] = (o, d, t)
    return out


def _stack(groups):
    names = list(groups)
    o = np.concatenate([groups[g][0] for g in names])
    d = np.concatenate([groups[g][1] for g in names])
    t = np.concatenate([groups[g][2] for g in names])
    label = np.concatenate([np.full(len(groups[g][0]), g) for g in names])
    return o, d, t, label


def by_group(v: Verdict, label):
    """Per ray group: (rays, wrong, capped, false hits, misses, ambiguous)."""
    m = v.masks
    return {g: (int((label == g).sum()), int(m["wrong"][label == g].sum()),
                int(m["capped"][label == g].sum()), int(m["false"][label == g].sum()),
                int(m["miss"][label == g].sum()), int(m["amb"][label == g].sum()))
            for g in dict.fromkeys(label)}


def union_surface(scene, form="primitives", depth=None):
    """(Surface, Fn) of the union of the scene, as primitives or as text."""
    tf = scene.table("union")
    if form == "text":
        f = parse(union_text(scene))
        surf = lgshape.Surface(f, bbox=tf.bbox, depth=depth)
        return surf, Fn(f)
    return lgshape.Surface(tf, depth=depth), Fn(tf)


def check_union(scene, rng, n, form="primitives", groups=("camera", "inside"), rays=None):
    """The union's trace against its closed-form oracle on the ray groups
    (or on ``rays``: (o, d, t_min)); returns (Verdict, per-group counts,
    Surface)."""
    surf, F = union_surface(scene, form)
    if rays is None:
        o, d, tm, label = _stack(scene_rays(scene, rng, surf.lo, surf.hi, n, groups))
    else:
        o, d, tm = rays
        label = np.full(len(o), "rays")
    res = surf.trace(o, d, t_min=tm)
    roots = union_oracle(scene, o, d, surf.lo, surf.hi, tm)
    v = judge(res, F, o, d, roots, surf.lo, surf.hi, tm)
    return v, by_group(v, label), surf


def check_scan(scene, rng, n, combine, k=0.05, threshold=0.3, form="primitives", steps=768,
               groups=("camera", "inside"), weights=None):
    """A smooth union or blend against the float64 scan."""
    kw = {"k": k} if combine == "smooth_union" else {"threshold": threshold}
    tf = scene.table(combine, **kw)
    if form == "text":
        f = parse(blend_text(scene, threshold))
        surf = lgshape.Surface(f, bbox=tf.bbox)
        F = Fn(f)
    else:
        surf = lgshape.Surface(tf)
        F = Fn(tf)
    o, d, tm, label = _stack(scene_rays(scene, rng, surf.lo, surf.hi, n, groups))
    res = surf.trace(o, d, t_min=tm)
    grow = k if combine == "smooth_union" else 0.0
    roots = scan_oracle(F, scene, o, d, surf.lo, surf.hi, grow, steps=steps, t_min=tm)
    v = judge(res, F, o, d, roots, surf.lo, surf.hi, tm, complete=False)
    return v, by_group(v, label), surf


def mixed_scene(rng, kind, n=6, spread=0.6):
    """A union of n parts of one kind near the origin, some overlapping;
    ``mixed``: 3 of every kind; ``rounded_box_torus``: n of each."""
    c = rng.uniform(-spread, spread, (n, 3))
    if kind == "sphere":
        return Scene.make(spheres=np.column_stack([c, rng.uniform(0.1, 0.3, n)]))
    if kind == "capsule":
        b = c + unit(rng.normal(size=(n, 3))) * rng.uniform(0.2, 0.6, (n, 1))
        return Scene.make(capsules=np.column_stack([c, b, rng.uniform(0.05, 0.15, n)]))
    if kind in ("box", "rounded_box"):
        h = rng.uniform(0.08, 0.3, (n, 3))
        rr = h.min(1) * rng.uniform(0.2, 0.9, n) if kind == "rounded_box" else np.zeros(n)
        return Scene.make(boxes=np.column_stack([c, h, rr]))
    if kind == "torus":
        R = rng.uniform(0.15, 0.35, n)
        return Scene.make(tori=np.column_stack([c, R, R * rng.uniform(0.15, 0.45, n)]))
    if kind == "rounded_box_torus":
        return _merge(mixed_scene(rng, "rounded_box", n, 0.3), mixed_scene(rng, "torus", n, 0.3))
    out = mixed_scene(rng, "sphere", 3)
    for k in ("capsule", "box", "rounded_box", "torus"):
        out = _merge(out, mixed_scene(rng, k, 3))
    return out


# ---------------------------------------------------------------------------
# t windows: t_min / t_max about each ray's first root
# ---------------------------------------------------------------------------

def window_rays(o, d, first, diag, seg_end):
    """Each ray repeated with windows about its oracle first root r (or
    about the middle of its segment where it has none): t_max just before
    and after r, t_min just after r and inside the part, an empty window."""
    tol = REL_TOL * diag
    r = np.where(np.isfinite(first), first, seg_end)
    wins = [(0.0, r + 5 * tol), (0.0, r - 5 * tol), (0.0, r + 1e-3 * diag),
            (r + 5 * tol, np.inf), (r + 0.01 * diag, np.inf), (r - 5 * tol, r + 5 * tol),
            (r + 1e-3 * diag, r - 1e-3 * diag)]
    n = len(o)
    O = np.tile(o, (len(wins), 1))
    D = np.tile(d, (len(wins), 1))
    TM = np.concatenate([np.broadcast_to(a, n) for a, _ in wins]).astype(np.float64)
    TX = np.concatenate([np.broadcast_to(b, n) for _, b in wins]).astype(np.float64)
    return O, D, np.maximum(TM, 0.0), TX


def check_windows(surf, F, o, d, roots_fn, complete=True):
    """Trace with the windows of :func:`window_rays`, judged against the
    oracle's roots (``roots_fn(o, d)``: every root along the ray in the
    box; the judge keeps those in the window)."""
    lo, hi = surf.lo, surf.hi
    roots = roots_fn(o, d)
    first = np.where(np.isfinite(roots).any(1), np.nanmin(np.where(np.isfinite(roots), roots, np.inf), 1),
                     np.inf)
    o64, d64 = o.astype(np.float64), d.astype(np.float64)
    t0, t1 = clip_to_box(o64, d64, lo, hi)
    O, D, TM, TX = window_rays(o, d, first, surf.diagonal, 0.5 * (t0 + np.maximum(t1, t0)))
    # float32 t_min / t_max as the kernel holds them
    TM, TX = f32(TM), np.where(np.isinf(TX), np.inf, f32(TX))
    res = surf.trace(O, D, t_min=TM, t_max=TX)
    R = np.tile(roots, (len(O) // len(o), 1))
    return judge(res, F, O, D, R, lo, hi, TM, TX, complete=complete)


# ---------------------------------------------------------------------------
# t_max: the first root before t_max is the first root for t_max = inf
# ---------------------------------------------------------------------------

#: t_max beyond the first root r (diagonals; "tol": 4x the tolerance), and
#: before it (negative): trace must return r for the first, a miss for the
#: others; occluded(t_max) must be True exactly for the first.
T_MAX_OFFSETS = ("4tol", 1e-4, 1e-2, 0.3, 3.0, "-4tol", -1e-2)


def check_t_max(surf, F, o, d, roots):
    """Trace each ray with t_max = inf, then with t_max at each of
    :data:`T_MAX_OFFSETS` from the t it found (the middle of its segment
    where it found none), with trace and occluded. Returns a dict:
    ``base`` (the t_max = inf Verdict against the oracle's ``roots``),
    ``pairs`` (ray x t_max pairs), ``trace_bad`` / ``occluded_bad``
    (answers that differ from the t_max = inf one: a hit exactly where
    t_inf < t_max, at t_inf to the tolerance), and the same counts on the
    rays the oracle finds ambiguous (``*_bad_ambiguous``: there trace must
    still agree with its t_max = inf answer, and occluded with the oracle:
    True only with a root before t_max, False only without a verified
    one), ``capped``, and an example."""
    lo, hi, diag = surf.lo, surf.hi, surf.diagonal
    base = surf.trace(o, d)
    v = judge(base, F, o, d, roots, lo, hi)
    h0, t_inf = np.asarray(base.hit), np.asarray(base.t64, np.float64)
    o64, d64 = o.astype(np.float64), d.astype(np.float64)
    a, b = clip_to_box(o64, d64, lo, hi)
    tol = REL_TOL * diag / np.linalg.norm(d64, axis=1)
    ref = np.where(h0, t_inf, np.where(b > a, 0.5 * (a + np.maximum(a, b)), 1.0))
    tms = []
    for k in T_MAX_OFFSETS:
        step = (4 * tol if k == "4tol" else -4 * tol) if isinstance(k, str) else k * diag
        tms.append(ref + step)
    n = len(o)
    O, D = np.tile(o, (len(tms), 1)), np.tile(d, (len(tms), 1))
    TM = np.concatenate(tms)
    H, T, AMB = np.tile(h0, len(tms)), np.tile(t_inf, len(tms)), np.tile(v.masks["amb"], len(tms))
    TOL = np.tile(tol, len(tms))
    r = surf.trace(O, D, t_max=TM)
    h, t = np.asarray(r.hit), np.asarray(r.t64, np.float64)
    want = H & (T < TM)
    with np.errstate(invalid="ignore"):
        tbad = (h != want) | (h & want & ~(np.abs(t - T) <= TOL))
    occ = np.asarray(surf.occluded(O, D, TM))
    # occluded against the t_max = inf trace; on rays whose first root is
    # ambiguous (a sliver trace may miss), against the oracle with the
    # contract's allowance instead: True needs a root before t_max, False
    # no verified one
    first_t = np.tile(v.masks["first_t"], len(tms))
    ver_t = np.tile(v.masks["ver_t"], len(tms))
    obad = np.where(AMB, (occ & ~(first_t < TM + TOL)) | (~occ & (ver_t < TM - TOL)), occ != want)
    ex = ""
    bad = tbad | obad
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        j = i % n
        ex = (f"ray {j}: o {o[j].tolist()} d {d[j].tolist()} t_inf {t_inf[j]!r} (hit {bool(h0[j])}), "
              f"t_max {TM[i]!r}: trace hit {bool(h[i])} t64 {t[i]!r}, occluded {bool(occ[i])}; "
              f"oracle roots {np.sort(roots[j][np.isfinite(roots[j])])[:4].tolist()}")
    return dict(base=v, pairs=len(O), trace_bad=int((tbad & ~AMB).sum()),
                occluded_bad=int((obad & ~AMB).sum()),
                trace_bad_ambiguous=int((tbad & AMB).sum()),
                occluded_bad_ambiguous=int((obad & AMB).sum()),
                capped=int(np.asarray(r.capped).sum()), example=ex)


def t_max_cases(rng, n):
    """The t_max cases: {name: (expression or TableForm, bbox, oracle
    roots_fn(surf, F, o, d), (o, d), search modes)}."""
    x, y, z = lgshape.x, lgshape.y, lgshape.z
    q = x ** 2 + y ** 2 + z ** 2
    cube = ((-1.2,) * 3, (1.2,) * 3)
    diag = 2.4 * math.sqrt(3)
    out = {}

    def poly(deg):
        return lambda surf, F, o, d: poly_oracle(F, deg, o, d, surf.lo, surf.hi)
    both = ("interval", "taylor")
    out["thin_shell"] = ((q - 1) ** 2 - 1e-8, cube, poly(4), camera_rays(rng, *cube, n), both)
    eps = 1e-6 * diag           # a shell 1e-6 of the diagonal thick: near-double pairs
    out["sliver_shell"] = ((q - 1) ** 2 - eps * eps, cube, poly(4), camera_rays(rng, *cube, n), both)
    out["close_roots"] = ((q - 1) * ((x - 1e-5) ** 2 + y ** 2 + z ** 2 - 1), cube, poly(4),
                          camera_rays(rng, *cube, n), both)
    tb = ((-1.54, -1.54, -0.48), (1.54, 1.54, 0.48))
    out["torus_grazing"] = (torus_expr((0, 0, 0), 1.0, 0.4), tb, poly(4),
                            torus_rays(rng, n, (0, 0, 0), 1.0, 0.4, 1.0, np.array(tb[0]),
                                       np.array(tb[1])), both)
    # two spheres 1e-6 of the diagonal apart as a min of distances (the
    # expression path): exit / entry pairs at the gap
    g = 1e-6 * diag
    e = lgshape.expr.node.minimum(lgshape.expr.node.sqrt((x + 0.5) ** 2 + y ** 2 + z ** 2) - 0.5,
                                  lgshape.expr.node.sqrt((x - 0.5 - g) ** 2 + y ** 2 + z ** 2) - 0.5)
    s2 = Scene.make(spheres=[[-0.5, 0, 0, 0.5], [0.5 + g, 0, 0, 0.5]])
    pts = np.array([0.5 * g, 0, 0]) + 0.05 * rng.normal(size=(n // 2, 3)) *         10 ** rng.uniform(-5, 0, (n // 2, 1))
    dd = unit(rng.normal(size=(n // 2, 3)))
    oc, dc = camera_rays(rng, *cube, n - n // 2)
    # from inside either ball, through the contact region: the first root
    # an exit, the next an entry across the gap
    rays = (np.concatenate([np.float32(pts - 0.05 * dd), oc]), np.concatenate([np.float32(dd), dc]))
    exact = np.abs(np.float32(s2.sphere[:, :3]) - s2.sphere[:, :3]).max() == 0
    assert exact
    out["near_touching_spheres"] = (e, cube, lambda surf, F, o, d: union_oracle(s2, o, d, surf.lo,
                                                                              surf.hi),
                                    rays, both)
    # a table: rounded boxes and tori, grazing rays
    s = mixed_scene(rng, "rounded_box_torus")
    tf = s.table("union")
    grp = scene_rays(s, rng, *tf.bbox, n, ("camera", "aimed", "grazing"))
    o_, d_, _, _ = _stack(grp)
    out["table_rounded_box_torus"] = (tf, None, lambda surf, F, o, d: union_oracle(s, o, d, surf.lo,
                                                                                 surf.hi),
                                      (o_, d_), ("interval",))
    return out


def run_t_max(name, search, rng, n):
    f, bbox, roots_fn, (o, d), _ = t_max_cases(rng, n)[name]
    surf = lgshape.Surface(f, bbox=bbox, search=search)
    F = Fn(f)
    return check_t_max(surf, F, o, d, roots_fn(surf, F, o, d))


# ---------------------------------------------------------------------------
# The attack classes: name -> fn(rng, n) -> Verdict
# ---------------------------------------------------------------------------

CLASSES = {}


def attack(name):
    def reg(fn):
        CLASSES[name] = fn
        return fn
    return reg


def _far_centre(off):
    return (off, -off, off / 2)


def _union_far(off, form):
    def run(rng, n):
        return check_union(random_scene(rng, _far_centre(off), n=16), rng, n, form)[0]
    return run


for _pos in (1e7, 3e7):
    attack(f"table_union_far_{_pos:g}")(_union_far(_pos, "primitives"))
    attack(f"table_union_text_far_{_pos:g}")(_union_far(_pos, "text"))


def _scan_far(off, combine, form="primitives"):
    def run(rng, n):
        s = random_scene(rng, _far_centre(off), n=8, blend=combine == "blend")
        return check_scan(s, rng, max(60, n // 3), combine, form=form)[0]
    return run


attack("table_smooth_union_far_1e7")(_scan_far(1e7, "smooth_union"))
attack("table_blend_far_1e7")(_scan_far(1e7, "blend"))
attack("table_blend_text_far_1e7")(_scan_far(1e7, "blend", "text"))


@attack("table_union_spanning_1e5")
def _spanning(rng, n):
    """Two clusters 1e5 apart in one table (diagonal 1.7e5, so the
    tolerance 0.17 is about a part's size: most roots are slivers by the
    contract's measure, ambiguous), camera rays at each cluster."""
    a = random_scene(rng, (0.0, 0.0, 0.0), n=8)
    b = random_scene(rng, (1e5, 1e5, -1e5), n=8)
    s = _merge(a, b)
    rays = [camera_rays(rng, *sc.table("union").bbox, n // 2, radius=1.0) for sc in (a, b)]
    o = np.concatenate([r[0] for r in rays])
    d = np.concatenate([r[1] for r in rays])
    return check_union(s, rng, n, rays=(o, d, np.zeros(len(o))))[0]


def _scaled_union(scale, shift=(0.0, 0.0, 0.0)):
    def run(rng, n):
        s = random_scene(rng, n=12).transformed(scale, shift)
        return check_union(s, rng, n, groups=("camera", "inside", "aimed", "surface"))[0]
    return run


for _s, _sh, _tag in ((1e-3, (0, 0, 0), "1e-3"), (1e3, (0, 0, 0), "1e3"),
                      (1e-3, (1e3, 1e3, -1e3), "1e-3_at_1e3"), (1e3, (1e6, 1e6, 1e6), "1e3_at_1e6")):
    attack(f"table_union_scaled_{_tag}")(_scaled_union(_s, _sh))


def _scaled_scan(combine, scale, shift=(0.0, 0.0, 0.0)):
    def run(rng, n):
        s = random_scene(rng, n=8, blend=combine == "blend").transformed(scale, shift)
        return check_scan(s, rng, max(60, n // 3), combine, k=0.05 * scale)[0]
    return run


for _s, _sh, _tag in ((1e-3, (0, 0, 0), "1e-3"), (1e3, (0, 0, 0), "1e3"),
                      (1.0, (1e6, -1e6, 5e5), "1_at_1e6")):
    for _c in ("smooth_union", "blend"):
        attack(f"table_{_c}_scaled_{_tag}")(_scaled_scan(_c, _s, _sh))


@attack("table_tiny_beside_big")
def _tiny(rng, n):
    """Spheres of radius 1e-5 .. 1e-3 of the diagonal on and beside the
    faces of boxes 100 to 10^4 times larger; rays aimed at the spheres."""
    big = Scene.make(boxes=[[0, 0, 0, 0.5, 0.5, 0.5, 0.0], [1.2, 0, 0, 0.3, 0.6, 0.2, 0.05]])
    m = 24
    r = 3.5 * 10 ** rng.uniform(-5, -3, m)
    axis = rng.integers(0, 3, m)
    c = rng.uniform(-0.45, 0.45, (m, 3))
    c[np.arange(m), axis] = rng.choice([-1.0, 1.0], m) * (0.5 + r * rng.uniform(0.0, 3.0, m))
    s = _merge(big, Scene.make(spheres=np.column_stack([c, r])))
    k = rng.integers(0, m, n)
    o = s.sphere[k, :3] + 0.5 * unit(rng.normal(size=(n, 3)))
    aim = s.sphere[k, :3] + s.sphere[k, 3:4] * 1.3 * unit(rng.normal(size=(n, 3))) * \
        rng.uniform(0, 1, (n, 1)) ** (1 / 3)
    return check_union(s, rng, n, rays=(np.float32(o), np.float32(unit(aim - o)), np.zeros(n)))[0]


@attack("table_near_touching")
def _near_touching(rng, n):
    """Pairs of sharp boxes and of spheres with gaps of 1e-7 .. 1e-3 of the
    diagonal between them: rays through the box gaps parallel to the faces
    (exactly, and tilted by 1e-3), and rays through the spheres' contact
    region in random directions."""
    gaps = 10.0 ** np.arange(-7, -2)
    scale = 4.0                       # about the scene's diagonal
    rows_b, rows_s = [], []
    for i, g in enumerate(gaps):
        x0 = -1.0 + 0.45 * i
        rows_b += [[x0, -0.6, 0.0, 0.1, 0.1, 0.1, 0.0],
                   [x0 + 0.2 + g * scale, -0.6, 0.0, 0.1, 0.1, 0.1, 0.0]]
        rows_s += [[x0, 0.6, 0.0, 0.1], [x0 + 0.2 + g * scale, 0.6, 0.0, 0.1]]
    s = Scene.make(spheres=rows_s, boxes=rows_b)
    per = max(1, n // (2 * len(gaps)))
    o, d = [], []
    for i, g in enumerate(gaps):
        mid = -1.0 + 0.45 * i + 0.1 + 0.5 * g * scale
        q = np.column_stack([mid + g * scale * rng.uniform(-0.6, 0.6, per), np.full(per, -1.0),
                             rng.uniform(-0.09, 0.09, per)])
        dd = np.tile([0.0, 1.0, 0.0], (per, 1)) + 1e-3 * rng.normal(size=(per, 3)) * \
            rng.choice([0, 1], (per, 1))
        o.append(q)
        d.append(unit(dd))
        p = np.array([mid, 0.6, 0.0]) + g * scale * rng.normal(size=(per, 3))
        dd = unit(rng.normal(size=(per, 3)))
        o.append(p - 0.5 * dd)
        d.append(dd)
    o, d = np.float32(np.concatenate(o)), np.float32(np.concatenate(d))
    return check_union(s, rng, n, rays=(o, d, np.zeros(len(o))))[0]


def _grazing(kind, off=0.0, scale=1.0, groups=("grazing", "aimed", "inside", "surface")):
    def run(rng, n):
        s = mixed_scene(rng, kind).transformed(scale, _far_centre(off))
        return check_union(s, rng, n, groups=groups)[0]
    return run


for _k in ("box", "rounded_box", "torus", "capsule", "sphere", "mixed", "rounded_box_torus"):
    attack(f"table_grazing_{_k}")(_grazing(_k))
attack("table_grazing_mixed_at_1e6")(_grazing("mixed", 1e6, groups=("aimed", "inside", "surface")))
attack("table_grazing_mixed_scaled_1e-3")(_grazing("mixed", 0.0, 1e-3))
attack("table_grazing_mixed_scaled_1e3")(_grazing("mixed", 0.0, 1e3))


@attack("table_face_planes")
def _face_planes(rng, n):
    """Axis-aligned rays lying exactly in the face planes of sharp and
    rounded boxes (F = 0, or F constant, along a whole stretch) and along
    their edges: tangent touches, which may be reported or not, but must
    end (no ray capped)."""
    s = Scene.make(boxes=[[-0.5, 0, 0, 0.25, 0.25, 0.25, 0.0], [0.5, 0, 0, 0.25, 0.25, 0.25, 0.0625],
                          [0, 0.5, 0.25, 0.125, 0.25, 0.125, 0.0]])
    o, d = [], []
    for row in s.box:
        c, h = row[:3], row[3:6] + row[6]
        for axis in range(3):
            for other in range(3):
                if other == axis:
                    continue
                m = max(1, n // 18)
                q = c + rng.uniform(-1, 1, (m, 3)) * h
                q[:, other] = c[other] + rng.choice([-1.0, 1.0], m) * h[other]
                q[:, axis] = -2.0
                dd = np.zeros((m, 3))
                dd[:, axis] = 1.0
                o.append(q)
                d.append(dd)
    o, d = np.float32(np.concatenate(o)), np.float32(np.concatenate(d))
    return check_union(s, rng, n, rays=(o, d, np.zeros(len(o))))[0]


@attack("table_torus_near_horn")
def _horn(rng, n):
    """Tori with r = (1 - 1e-3 .. 1e-6) R (the hole nearly closed: near
    double roots at the centre), rays near the axis and from around."""
    R = 0.3
    eps = 10.0 ** -np.arange(3, 7)
    c = np.column_stack([np.linspace(-1.2, 1.2, len(eps)), np.zeros(len(eps)), np.zeros(len(eps))])
    s = Scene.make(tori=np.column_stack([c, np.full(len(eps), R), R * (1 - eps)]))
    m = n // (2 * len(eps))
    o, d = [], []
    for row in s.torus:
        q = row[:3] + np.column_stack([R * 1e-3 * rng.normal(size=(m, 2)), np.full(m, 1.0)])
        dd = np.column_stack([1e-3 * rng.normal(size=(m, 2)), -np.ones(m)])
        o.append(q)
        d.append(unit(dd))
    oc, dc = camera_rays(rng, s.table("union").bbox[0], s.table("union").bbox[1], n // 2)
    o, d = np.float32(np.concatenate(o + [oc])), np.float32(np.concatenate(d + [dc]))
    return check_union(s, rng, n, rays=(o, d, np.zeros(len(o))))[0]


@attack("table_capsule_degenerate")
def _caps(rng, n):
    """Capsules of length 0, 1e-7, 1e-4 and 1e-1 (1 / |b - a|^2 up to 1e14,
    or 0 for a point: a sphere), grazing and camera rays."""
    L = np.array([0.0, 1e-7, 1e-4, 1e-1] * 3)
    a = rng.uniform(-0.6, 0.6, (len(L), 3))
    b = a + unit(rng.normal(size=(len(L), 3))) * L[:, None]
    s = Scene.make(capsules=np.column_stack([a, b, rng.uniform(0.05, 0.2, len(L))]))
    return check_union(s, rng, n, groups=("camera", "aimed", "inside", "surface"))[0]


@attack("table_box_rounding_tiny")
def _tiny_round(rng, n):
    """Rounded boxes whose rounding is 1e-7 .. 1e-4 of their size (near
    kinks at the edges), grazing rays."""
    k = 8
    c = rng.uniform(-0.6, 0.6, (k, 3))
    h = rng.uniform(0.1, 0.3, (k, 3))
    rr = h.min(1) * 10 ** rng.uniform(-7, -4, k)
    s = Scene.make(boxes=np.column_stack([c, h, rr]))
    return check_union(s, rng, n, groups=("camera", "aimed", "grazing", "surface"))[0]


@attack("table_blend_threshold_1e-6")
def _blend_low(rng, n):
    """A blend with threshold 1e-6: the surface lies where the kernels are
    nearly 0, flat (K ~ 8 (1 - q)^3)."""
    s = random_scene(rng, n=6, blend=True, sharp=False)
    return check_scan(s, rng, max(60, n // 3), "blend", threshold=1e-6)[0]


@attack("table_blend_threshold_near_peak")
def _blend_peak(rng, n):
    """A blend of well separated spheres with threshold 1 - 1e-6: each
    surface a tiny sphere (radius 6e-4 of the kernel's) about its centre,
    where the kernel is flat; rays aimed at the centres."""
    c = np.stack(np.meshgrid([-0.6, 0.6], [-0.6, 0.6], [0.0], indexing="ij"), -1).reshape(-1, 3)
    s = Scene.make(spheres=np.column_stack([c, np.full(len(c), 0.4)]))
    thr = 1 - 1e-6
    tf = s.table("blend", threshold=thr)
    surf = lgshape.Surface(tf)
    F = Fn(tf)
    k = rng.integers(0, len(c), n)
    o = c[k] + unit(rng.normal(size=(n, 3))) * 0.9
    aim = c[k] + 3e-4 * rng.normal(size=(n, 3))
    o, d = np.float32(o), np.float32(unit(aim - o))
    res = surf.trace(o, d)
    roots = scan_oracle(F, s, o, d, surf.lo, surf.hi, 0.0, steps=4096)
    # the scan cannot see a sphere 1e-4 wide at 4096 steps everywhere: add
    # the closed form (|p - c| = q R with K(q) = threshold, one kernel only)
    q = math.sqrt(1 - thr ** (1 / 3)) * 0.4
    ex = np.concatenate(ball_intervals(o.astype(np.float64), d.astype(np.float64), c,
                                       np.full(len(c), q)), 1)
    roots = np.concatenate([roots, ex], 1)
    return judge(res, F, o, d, roots, surf.lo, surf.hi, complete=False)


@attack("table_blend_weights")
def _blend_w(rng, n):
    """A weighted blend (weights 1e-3 .. 1e3, some negative: subtractive
    kernels) of spheres and capsules."""
    m = 16
    c = rng.uniform(-0.6, 0.6, (m, 3))
    w = rng.choice([-1.0, 1.0], m, p=[0.3, 0.7]) * 10 ** rng.uniform(-1, 3, m)
    parts = [P.spheres(f32(c), f32(rng.uniform(0.2, 0.4, m)), weights=w)]
    tf = P.blend(*parts, threshold=0.5)
    surf = lgshape.Surface(tf)
    F = Fn(tf)
    o, d, tm, label = _stack(scene_rays(Scene(sphere=np.column_stack([f32(c), parts[0].rows[:, 3]])),
                                        rng, surf.lo, surf.hi, n // 2, ("camera", "inside")))
    res = surf.trace(o, d, t_min=tm)
    sc = Scene(sphere=parts[0].rows)
    roots = scan_oracle(F, sc, o, d, surf.lo, surf.hi, 0.0, steps=2048, t_min=tm)
    return judge(res, F, o, d, roots, surf.lo, surf.hi, tm, complete=False)


@attack("table_smooth_union_box")
def _smooth_box(rng, n):
    """A smooth union of 16 nearly coincident spheres (radius 0.1, k = 0.8):
    each fold lowers f by up to k / 4 below the previous result, so f
    reaches min_i d_i - k (not - k / 4), and the surface lies past the
    builder's box (k / 4 beyond the parts, plus 2%). Oracle: the float64
    scan of f along the whole line (not only in the box): rays whose first
    root lies outside the builder's box count as misses."""
    m = 16
    c = 1e-3 * rng.normal(size=(m, 3))
    s = Scene.make(spheres=np.column_stack([c, np.full(m, 0.1)]))
    tf = s.table("smooth_union", k=0.8)
    surf = lgshape.Surface(tf)
    F = Fn(tf)
    o32, d32 = camera_rays(rng, surf.lo, surf.hi, n, radius=3.0)
    o, d = o32.astype(np.float64), d32.astype(np.float64)
    big = (np.full(3, -3.0), np.full(3, 3.0))
    t0, t1 = clip_to_box(o, d, *big)
    roots = scan_roots(F, o, d, t0, t1, steps=2048)
    v = judge(surf.trace(o32, d32), F, o32, d32, roots, *big, complete=False)
    v.example = (f"box {tuple(np.round(surf.lo, 3))}..{tuple(np.round(surf.hi, 3))}, "
                 f"f at (hi_x, 0, 0) = {float(F(surf.hi[0], 0.0, 0.0)):.3g} (< 0: the surface "
                 f"passes the box); " + v.example)
    return v


@attack("table_smooth_union_tiny_k")
def _smooth_tiny(rng, n):
    """A smooth union with k = 1e-6 of the diagonal (nearly the union, with
    creases rounded at the tolerance's scale)."""
    s = random_scene(rng, n=6, sharp=False)
    diag = float(np.linalg.norm(np.subtract(*s.table("union").bbox)))
    return check_scan(s, rng, max(60, n // 3), "smooth_union", k=1e-6 * diag)[0]


@attack("table_windows")
def _twin(rng, n):
    """t windows (t_min, t_max just before / after the first root, inside
    a part, empty) on a mixed union, rays from around and inside."""
    s = mixed_scene(rng, "mixed")
    surf, F = union_surface(s)
    o1, d1 = camera_rays(rng, surf.lo, surf.hi, n // 14)
    o2 = np.float32(inside_points(s, rng, n // 14))
    d2 = np.float32(unit(rng.normal(size=(len(o2), 3))))
    o, d = np.concatenate([o1, o2]), np.concatenate([d1, d2])
    return check_windows(surf, F, o, d, lambda o_, d_: union_oracle(s, o_, d_, surf.lo, surf.hi))


# -- rays through the singular points of the distances ---------------------------
#
# Where a primitive's distance has no slope (a torus's axis and core circle,
# a capsule's segment, a box's centre lines, centre planes and inner edges,
# a sphere's centre), its derivative rule reads 0 / 0 (sqrt at 0) and the
# interval rules of its slope are unbounded. Rays along and across those
# sets, in unions, smooth unions and blends, in a normal box and in a flat
# one (a slab 2^-9 thick about the plane z = 0 that holds every part's
# centre). Every value is a multiple of 2^-10 and every direction one of
# 2^-2, so the rays meet the singular points exactly (no float32 rounding
# moves them off).

def dyadic(v, bits=10):
    """v rounded to a multiple of 2^-bits (exact in float32 near 1, and so
    are the sums and differences of such values that the rays use)."""
    return np.round(np.asarray(v, np.float64) * 2.0 ** bits) / 2.0 ** bits


#: The flat box's half thickness about z = 0 (2^-10, as the issue's 1.2e-3).
FLAT_HALF = 2.0 ** -10


def singular_scene(rng, n=4, flat=False, blend=False, spread=0.35):
    """n primitives of each kind clustered about the origin (so that one's
    singular set runs through the others), every value dyadic: spheres;
    capsules, half of them along an axis; boxes, half sharp (a blend's all
    rounded: their rounding is the radius of influence); tori (axes along z,
    as the builder's). ``flat``: every centre, capsule and torus in the
    plane z = 0. ``blend``: radii of influence twice the sizes."""
    g = 2.0 if blend else 1.0

    def at(k):
        c = rng.uniform(-spread, spread, (k, 3))
        if flat:
            c[:, 2] = 0.0
        return dyadic(c)
    sph = np.column_stack([at(n), dyadic(g * rng.uniform(0.1, 0.25, n))])
    a = at(n)
    axis = np.eye(3)[rng.integers(0, 2 if flat else 3, n)] * rng.choice([-1.0, 1.0], (n, 1))
    free = unit(rng.normal(size=(n, 3)) * (np.array([1.0, 1.0, 0.0]) if flat else 1.0))
    dirs = np.where((np.arange(n) % 2 == 0)[:, None], axis, free)
    b = dyadic(a + dirs * rng.uniform(0.2, 0.5, (n, 1)))
    cap = np.column_stack([a, b, dyadic(g * rng.uniform(0.04, 0.1, n))])
    h = dyadic(rng.uniform(0.08, 0.25, (n, 3)))
    rr = dyadic(h.min(1) * rng.uniform(0.5 if blend else 0.2, 0.9, n))
    if not blend:
        rr = np.where(np.arange(n) % 2 == 0, 0.0, rr)
    box = np.column_stack([at(n), h, np.maximum(rr, 0.0 if not blend else 2.0 ** -10)])
    R = dyadic(rng.uniform(0.1, 0.25, n))
    r = np.minimum(dyadic(R * rng.uniform(0.15, 0.6 if blend else 0.45, n)), R - 2.0 ** -10)
    tor = np.column_stack([at(n), R, np.maximum(r, 2.0 ** -10)])
    s = Scene.make(sph, cap, box, tor)
    s.check_parts()
    return s


def flat_box(bbox):
    """The flat box: the builder's box in x and y, z in +-FLAT_HALF."""
    lo, hi = np.array(bbox[0], np.float64), np.array(bbox[1], np.float64)
    lo[2], hi[2] = -FLAT_HALF, FLAT_HALF
    return tuple(lo), tuple(hi)


def _quarter_dirs(rng, m, flat):
    """m directions with components in {-1, -3/4, ..., 1} (exact; not unit),
    none zero; ``flat``: in the plane z = 0."""
    d = rng.integers(-4, 5, (m, 3)) / 4.0
    if flat:
        d[:, 2] = 0.0
    zero = ~d.any(1)
    d[zero, 0] = 1.0
    return d


def _axis_dirs(rng, m, flat, along=None):
    """m axis directions (+-e_i; ``along``: that axis only; ``flat``: z
    for rays across the slab, x or y in it, half each)."""
    if along is not None:
        i = np.full(m, along)
    elif flat:
        i = np.where(rng.uniform(size=m) < 0.5, 2, rng.integers(0, 2, m))
    else:
        i = rng.integers(0, 3, m)
    return np.eye(3)[i] * rng.choice([-1.0, 1.0], (m, 1))


def singular_points(scene: Scene, rng, m, flat):
    """Singular points of the scene's distances with the directions that
    run along their singular set (axis-parallel) or cross it (oblique):
    {group: (points, directions)}, about m per group."""
    out = {}

    def pick(rows):
        return rows[rng.integers(0, len(rows), m)]
    sph, cap, box, tor = (pick(getattr(scene, k)) for k in ("sphere", "capsule", "box", "torus"))
    # a sphere's centre: along the axes, and obliquely
    out["sphere_centre_axis"] = (sph[:, :3], _axis_dirs(rng, m, flat))
    out["sphere_centre_oblique"] = (sph[:, :3], _quarter_dirs(rng, m, flat))
    # a torus's axis: along it (through the slab where flat), across it
    # (through the centre, or above and below it), and its core circle
    w = np.zeros(m) if flat else dyadic(tor[:, 4] * rng.uniform(-2.0, 2.0, m))
    axis_pt = tor[:, :3] + np.column_stack([np.zeros((m, 2)), w])
    out["torus_axis_along"] = (axis_pt, _axis_dirs(rng, m, False, along=2))
    out["torus_axis_across"] = (axis_pt, _quarter_dirs(rng, m, flat))
    k = rng.integers(0, 4, m)
    ring = np.array([[1.0, 0, 0], [0, 1.0, 0], [-1.0, 0, 0], [0, -1.0, 0]])[k]
    tangent = np.array([[0, 1.0, 0], [-1.0, 0, 0], [0, -1.0, 0], [1.0, 0, 0]])[k]
    core = tor[:, :3] + tor[:, 3:4] * ring
    dc = np.where((rng.uniform(size=m) < 0.5)[:, None], np.array([0, 0, 1.0]), tangent)
    out["torus_core_axis"] = (core, dc * rng.choice([-1.0, 1.0], (m, 1)))
    out["torus_core_oblique"] = (core, _quarter_dirs(rng, m, flat))
    # a capsule's segment: along it (its ends and inner points), across it
    s = rng.choice([0.0, 0.25, 0.5, 0.75, 1.0], m)
    seg = cap[:, :3] + s[:, None] * cap[:, 3:6]
    out["capsule_segment_along"] = (seg, cap[:, 3:6] * rng.choice([-1.0, 1.0], (m, 1)))
    out["capsule_segment_across"] = (seg, _quarter_dirs(rng, m, flat))
    # a box's centre (its centre lines and planes), and its inner box's
    # edges and corners (a sharp box's own: on the surface)
    out["box_centre_axis"] = (box[:, :3], _axis_dirs(rng, m, flat))
    dq = _quarter_dirs(rng, m, flat)
    plane = rng.integers(0, 3, m)
    if not flat:           # half of them in a centre plane (d_i = 0 there)
        dq[np.arange(m), plane] = np.where(rng.uniform(size=m) < 0.5, 0.0, dq[np.arange(m), plane])
        dq[~dq.any(1), (plane[~dq.any(1)] + 1) % 3] = 1.0
    out["box_centre_oblique"] = (box[:, :3], dq)
    e = box[:, 3:6]
    sg = rng.choice([-1.0, 1.0], (m, 3))
    along = 2 if flat else rng.integers(0, 3, m)
    edge = box[:, :3] + sg * e
    edge[np.arange(m), along] = box[np.arange(m), along] if flat else \
        box[np.arange(m), along] + dyadic(rng.uniform(-1, 1, m) * e[np.arange(m), along])
    out["box_edge_axis"] = (edge, np.eye(3)[np.broadcast_to(along, m)] * rng.choice([-1.0, 1.0], (m, 1)))
    corner = box[:, :3] + sg * e
    if flat:
        corner[:, 2] = 0.0
    out["box_corner_oblique"] = (corner, _quarter_dirs(rng, m, flat))
    return out


def singular_rays(scene: Scene, rng, n, flat=False):
    """Rays through the singular points (:func:`singular_points`), about n
    in all: {group: (o32, d32, t_min)}, each point met at t = 1 from
    o = p - d (exact), half of the rays with t_min = 0 and half starting at
    the point itself (o = p)."""
    pts = singular_points(scene, rng, max(2, n // 24), flat)
    out = {}
    for name, (p, d) in pts.items():
        o = np.concatenate([p - d, p])
        dd = np.concatenate([d, d])
        assert np.array_equal(np.float32(o).astype(np.float64), o), "ray origins not exact"
        out[name] = (np.float32(o), np.float32(dd), np.zeros(len(o)))
    return out


def check_singular(rng, n, combine, form="primitives", flat=False, k=0.05, threshold=0.3,
                   steps=2048):
    """The scene of :func:`singular_scene` as a union (closed-form oracle),
    a smooth union or a blend (the float64 scan of f, sign changes
    bisected) on :func:`singular_rays`; returns (Verdict, per-group counts,
    Surface)."""
    blend = combine == "blend"
    s = singular_scene(rng, flat=flat, blend=blend)
    kw = {"k": k} if combine == "smooth_union" else {"threshold": threshold} if blend else {}
    tf = s.table(combine, **kw)
    bbox = flat_box(tf.bbox) if flat else tf.bbox
    if form == "text":
        f = parse(union_text(s) if combine == "union" else blend_text(s, threshold))
    else:
        f = tf
    surf = lgshape.Surface(f, bbox=bbox)
    F = Fn(f)
    o, d, tm, label = _stack(singular_rays(s, rng, n, flat))
    res = surf.trace(o, d, t_min=tm)
    if combine == "union":
        roots = union_oracle(s, o, d, surf.lo, surf.hi, tm)
        v = judge(res, F, o, d, roots, surf.lo, surf.hi, tm)
    else:
        grow = k if combine == "smooth_union" else 0.0
        roots = scan_oracle(F, s, o, d, surf.lo, surf.hi, grow, steps=steps, t_min=tm)
        v = judge(res, F, o, d, roots, surf.lo, surf.hi, tm, complete=False)
    return v, by_group(v, label), surf


def _singular(combine, form="primitives", flat=False):
    def run(rng, n):
        return check_singular(rng, n, combine, form, flat)[0]
    run.__doc__ = (f"Rays through the singular points of the distances (see above) of a "
                   f"{combine.replace('_', ' ')} ({form}) in a {'flat' if flat else 'normal'} box.")
    return run


SINGULAR = [(c, fm, fl) for c, fm in (("union", "primitives"), ("union", "text"),
                                      ("smooth_union", "primitives"), ("blend", "primitives"),
                                      ("blend", "text")) for fl in (False, True)]
for _c, _fm, _fl in SINGULAR:
    attack(f"table_singular_{_c}{'_text' if _fm == 'text' else ''}{'_flat' if _fl else ''}")(
        _singular(_c, _fm, _fl))


@attack("table_singular_issue")
def _singular_issue(rng, n):
    """The issue's scene (two tori in a blend, threshold 0.2, in the flat box
    z in +-0.0012) with its ray down the first torus's axis, and rays down
    both axes and across them in the box's plane from around."""
    c = np.array([[-0.7028555274009705, 0.39704275131225586, 0.0],
                  [-0.7510408163070679, 0.2938717305660248, 0.0]])
    R = np.array([0.051894959062337875, 0.08862226456403732])
    r = np.array([0.024300141260027885, 0.03918442875146866])
    s = Scene.make(tori=np.column_stack([c, R, r]))
    tf = s.table("blend", threshold=0.2)
    surf = lgshape.Surface(tf, bbox=((-1.2, -1.2, -0.0012), (1.2, 1.2, 0.0012)))
    F = Fn(tf)
    m = max(1, n // 4)
    k = rng.integers(0, 2, m)
    z = np.float32(rng.uniform(0.0012, 2.0, m)).astype(np.float64)
    o = [np.array([[c[0, 0], c[0, 1], 1.0194339752197266]]),
         np.column_stack([s.torus[k, :2], z]), np.column_stack([s.torus[k, :2], -z])]
    d = [np.array([[0.0, 0.0, -1.0]]), np.tile([0.0, 0.0, -1.0], (m, 1)),
         np.tile([0.0, 0.0, 1.0], (m, 1))]
    dq = _quarter_dirs(rng, 2 * m, True)
    kk = rng.integers(0, 2, 2 * m)
    o.append(s.torus[kk, :3] - dq)
    d.append(dq)
    o, d = np.float32(np.concatenate(o)), np.float32(np.concatenate(d))
    res = surf.trace(o, d)
    roots = scan_oracle(F, s, o, d, surf.lo, surf.hi, 0.0, steps=4096)
    return judge(res, F, o, d, roots, surf.lo, surf.hi, complete=False)


# -- the polynomial path -------------------------------------------------------

def torus_expr(c, R, r, scale=1.0):
    x, y, z = lgshape.x, lgshape.y, lgshape.z
    X, Y, Z = (x - c[0]) / scale, (y - c[1]) / scale, (z - c[2]) / scale
    q = X ** 2 + Y ** 2
    return (q + Z ** 2 + (R * R - r * r)) ** 2 - 4 * R * R * q


def check_poly(e, bbox, degree, o32, d32, t_min=0.0, search="interval"):
    surf = lgshape.Surface(e, bbox=bbox, search=search)
    F = Fn(e)
    roots = poly_oracle(F, degree, o32, d32, surf.lo, surf.hi, t_min)
    return judge(surf.trace(o32, d32, t_min=t_min), F, o32, d32, roots, surf.lo, surf.hi, t_min)


def torus_rays(rng, n, c, R, r, scale, lo, hi, aimed=True):
    diag = float(np.linalg.norm(hi - lo))
    o1, d1 = camera_rays(rng, lo, hi, n // 2)
    u, v = rng.uniform(0, 2 * np.pi, (2, n // 24 + 1))
    ring = np.stack([np.cos(u), np.sin(u), 0 * u], 1)
    nr = np.cos(v)[:, None] * ring + np.sin(v)[:, None] * np.array([0, 0, 1.0])
    p = np.asarray(c) + scale * (R * ring + r * nr)
    o2, d2 = grazing_rays(rng, p, nr, diag * 10.0 ** np.arange(-7.0, -1.0), 0.3 * diag, aimed=aimed)
    return np.concatenate([o1, o2]), np.concatenate([d1, d2])


def _poly_torus(off, scale=1.0, search="interval"):
    def run(rng, n):
        c = np.array(_far_centre(off))
        R, r = 1.0, 0.4
        h = 1.1 * (R + r) * scale
        ext = np.array([h, h, 1.2 * r * scale])
        bbox = (tuple(c - ext), tuple(c + ext))
        o, d = torus_rays(rng, n, c, R, r, scale, c - ext, c + ext, aimed=off != 0 or scale != 1)
        return check_poly(torus_expr(c, R, r, scale), bbox, 4, o, d, search=search)
    return run


for _pos, _s, _tag in ((0.0, 1.0, "at_0"), (1e4, 1.0, "at_1e4"), (1e6, 1.0, "at_1e6"),
                       (0.0, 1e-3, "scaled_1e-3"), (0.0, 1e3, "scaled_1e3"),
                       (1e3, 1e-3, "scaled_1e-3_at_1e3")):
    attack(f"poly_torus_{_tag}")(_poly_torus(_pos, _s))
attack("poly_torus_taylor")(_poly_torus(0.0, 1.0, "taylor"))
attack("poly_torus_taylor_at_1e4")(_poly_torus(1e4, 1.0, "taylor"))


def _poly_shell(off, eps):
    def run(rng, n):
        x, y, z = lgshape.x, lgshape.y, lgshape.z
        c = np.array([off, off, -off])
        e = ((x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2 - 1) ** 2 - eps * eps
        bbox = (tuple(c - 1.2), tuple(c + 1.2))
        o, d = camera_rays(rng, *bbox, n)
        return check_poly(e, bbox, 4, o, d)
    return run


for _pos in (0.0, 1e4, 1e6):
    attack(f"poly_thin_shell_at_{_pos:g}")(_poly_shell(_pos, 1e-4))
attack("poly_sliver_shell")(_poly_shell(0.0, 4e-6))


@attack("poly_nested_spheres_deg8")
def _nested(rng, n):
    """Four concentric spheres of radii 1, 1 + 1e-5, 1 + 1e-3, 1.1 as one
    polynomial of degree 8 (close roots in pairs)."""
    x, y, z = lgshape.x, lgshape.y, lgshape.z
    q = x ** 2 + y ** 2 + z ** 2
    e = (q - 1) * (q - (1 + 1e-5) ** 2) * (q - (1 + 1e-3) ** 2) * (q - 1.21)
    bbox = ((-1.2,) * 3, (1.2,) * 3)
    o, d = camera_rays(rng, *bbox, n)
    return check_poly(e, bbox, 8, o, d)


@attack("poly_tangle_at_1e4")
def _tangle_far(rng, n):
    """The tangle cube moved to (1e4, -1e4, 1e4) (written with x - 1e4 ...)."""
    x, y, z = lgshape.x, lgshape.y, lgshape.z
    c = np.array([1e4, -1e4, 1e4])
    X, Y, Z = x - c[0], y - c[1], z - c[2]
    e = X ** 4 - 5 * X ** 2 + Y ** 4 - 5 * Y ** 2 + Z ** 4 - 5 * Z ** 2 + 11.8
    bbox = (tuple(c - 2.5), tuple(c + 2.5))
    o, d = camera_rays(rng, *bbox, n)
    return check_poly(e, bbox, 4, o, d)


@attack("poly_tangle_origin_on_surface")
def _tangle_on(rng, n):
    """The tangle cube: origins on the surface (Newton-projected, float32),
    rays inward, outward and tangent, t_min 0 and 1e-3 diagonals."""
    spec = lgshape.surfaces.tangle()
    F = Fn(spec.expr)
    g = list(gradient(spec.expr))

    def grad(p):
        return np.stack([np.broadcast_to(v, len(p)) for v in evaluate(g, dict(zip("xyz", p.T)))], 1)
    p = rng.uniform(-2.2, 2.2, (4 * n, 3))
    for _ in range(30):
        gv = grad(p)
        p = p - (F(*p.T) / (gv * gv).sum(1))[:, None] * gv
    p = p[np.abs(F(*p.T)) < 1e-9][: max(1, n // 6)]
    gv = unit(grad(p))
    o = np.float32(np.concatenate([p, p, p]))
    d = np.float32(np.concatenate([-gv, gv, perpendicular(gv, rng)]))
    diag = float(np.linalg.norm(np.subtract(spec.bbox[1], spec.bbox[0])))
    return _sum([check_poly(spec.expr, spec.bbox, 4, o, d, t_min=tm) for tm in (0.0, 1e-3 * diag)])


@attack("poly_windows")
def _pwin(rng, n):
    """t windows on the torus polynomial (camera and grazing rays)."""
    c, R, r = (0.0, 0.0, 0.0), 1.0, 0.4
    e = torus_expr(c, R, r)
    ext = np.array([1.54, 1.54, 0.48])
    surf = lgshape.Surface(e, bbox=(tuple(-ext), tuple(ext)))
    F = Fn(e)
    o, d = torus_rays(rng, n // 7, c, R, r, 1.0, -ext, ext)
    return check_windows(surf, F, o, d, lambda o_, d_: poly_oracle(F, 4, o_, d_, surf.lo, surf.hi))


def _sum(vs):
    out = vs[0]
    for v in vs[1:]:
        out = Verdict(out.rays + v.rays, out.wrong + v.wrong, out.capped + v.capped,
                      out.false_hits + v.false_hits, out.misses + v.misses,
                      out.ambiguous + v.ambiguous, out.verified + v.verified,
                      out.hidden + v.hidden, out.touches + v.touches,
                      max(out.max_dist, v.max_dist),
                      max(out.max_dist32, v.max_dist32),
                      (out.iterations * out.rays + v.iterations * v.rays) / (out.rays + v.rays),
                      out.example or v.example)
    return out


# -- the sinusoid path -----------------------------------------------------------

def gyroid_expr(c, freq=2.0, level=0.0):
    from lgshape.expr.node import cos, sin
    x, y, z = lgshape.x, lgshape.y, lgshape.z
    X, Y, Z = freq * (x - c[0]), freq * (y - c[1]), freq * (z - c[2])
    return sin(X) * cos(Y) + sin(Y) * cos(Z) + sin(Z) * cos(X) - level


def schwarz_p_expr(level):
    from lgshape.expr.node import cos
    x, y, z = lgshape.x, lgshape.y, lgshape.z
    return cos(2 * x) + cos(2 * y) + cos(2 * z) - level


def _newton_points(e, F, lo, hi, rng, n):
    """Points of f = 0 in the box (Newton from random points) and their
    unit normals."""
    g = list(gradient(e))

    def grad(p):
        return np.stack([np.broadcast_to(v, len(p)) for v in evaluate(g, dict(zip("xyz", p.T)))], 1)
    p = lo + (hi - lo) * rng.uniform(0.2, 0.8, (8 * n, 3))
    for _ in range(30):
        gv = grad(p)
        p = p - (F(*p.T) / (gv * gv).sum(1))[:, None] * gv
    gv = grad(p)
    ok = (np.abs(F(*p.T)) < 1e-10) & (np.linalg.norm(gv, axis=1) > 0.1) & np.all((p > lo) & (p < hi), 1)
    return p[ok][:n], unit(gv[ok][:n])


def check_trig(e, bbox, rng, n, freq, grazing=False, aimed=False, need_trig=True):
    surf = lgshape.Surface(e, bbox=bbox)
    if need_trig:
        assert surf.ray_trig is not None, "not the sinusoid path"
    F = Fn(e)
    lo, hi, diag = surf.lo, surf.hi, surf.diagonal
    if grazing:
        p, nr = _newton_points(e, F, lo, hi, rng, n // 12 + 1)
        o, d = grazing_rays(rng, p, nr, diag * 10.0 ** np.arange(-7.0, -1.0), 0.05 * diag,
                            aimed=aimed)
    else:
        o, d = camera_rays(rng, lo, hi, n)
    # the scan's step: 1/40 of the shortest period along the ray
    steps = int(40 * freq * diag / (2 * np.pi)) + 64
    roots = sweep_oracle(F, o, d, lo, hi, steps, max_roots=4)
    return judge(surf.trace(o, d), F, o, d, roots, lo, hi, complete=False)


def _gyroid(off, freq=2.0, half=1.5, level=0.0, grazing=False):
    def run(rng, n):
        c = np.array([off, -off, off])
        bbox = (tuple(c - half), tuple(c + half))
        return check_trig(gyroid_expr(c, freq, level), bbox, rng, n, freq, grazing,
                          aimed=off != 0)
    return run


for _pos in (0.0, 1e4, 1e6):
    attack(f"trig_gyroid_at_{_pos:g}")(_gyroid(_pos))
attack("trig_gyroid_grazing")(_gyroid(0.0, grazing=True))
attack("trig_gyroid_grazing_at_1e4")(_gyroid(1e4, grazing=True))
attack("trig_gyroid_freq_1e3")(_gyroid(0.0, freq=2e3, half=1.5e-3))
attack("trig_gyroid_level_1.4")(_gyroid(0.0, level=1.4))
attack("trig_gyroid_level_1.4_grazing")(_gyroid(0.0, level=1.4, grazing=True))


@attack("trig_schwarz_p_level_2.99")
def _schwarz(rng, n):
    """Schwarz's P at level 2.99 (cos 2x + cos 2y + cos 2z = 2.99): tiny
    closed blobs (radius ~0.07) about the lattice points, grazed."""
    e = schwarz_p_expr(2.99)
    bbox = ((-1.7,) * 3, (1.7,) * 3)
    return _sum([check_trig(e, bbox, rng, n // 2, 2.0), check_trig(e, bbox, rng, n // 2, 2.0,
                                                                   grazing=True)])


@attack("trig_gyroid_raw_at_1e4")
def _raw(rng, n):
    """The gyroid as written, sin(2x) cos(2y) + ..., in a box at (1e4,
    -1e4, 1e4): phases of 2e4 in the sinusoids (the float64 oracle has
    them exactly)."""
    c = np.array([1e4, -1e4, 1e4])
    e = gyroid_expr((0.0, 0.0, 0.0))
    return check_trig(e, (tuple(c - 1.5), tuple(c + 1.5)), rng, n, 2.0)


@attack("trig_windows")
def _trwin(rng, n):
    """t windows on the gyroid (camera rays)."""
    e = gyroid_expr((0.0, 0.0, 0.0))
    surf = lgshape.Surface(e, bbox=((-1.5,) * 3, (1.5,) * 3))
    F = Fn(e)
    o, d = camera_rays(rng, surf.lo, surf.hi, n // 7)
    steps = int(40 * 2.0 * surf.diagonal / (2 * np.pi)) + 64
    return check_windows(surf, F, o, d, lambda o_, d_: sweep_oracle(F, o_, d_, surf.lo, surf.hi,
                                                                    steps), complete=False)


# ---------------------------------------------------------------------------
# The command line
# ---------------------------------------------------------------------------

HEADER = (f"{'class':36} {'rays':>6} {'wrong':>6} {'capped':>6} {'false':>6} {'missed':>6}"
          f" {'ambig':>6} {'max dist':>9} {'iters':>7} {'time':>6}")


def run_all(names, n, seed, log=print):
    rows = []
    for i, name in enumerate(names):
        rng = np.random.default_rng([seed, i])
        t = time.perf_counter()
        try:
            v, err = CLASSES[name](rng, n), None
        except Exception as exc:            # an attack that breaks a build is a finding too
            v, err = None, f"{type(exc).__name__}: {exc}"
        dt = time.perf_counter() - t
        rows.append((name, v, err, dt))
        if v is not None:
            log(f"{name:36} {v.rays:6d} {v.wrong:6d} {v.capped:6d} {v.false_hits:6d} {v.misses:6d}"
                f" {v.ambiguous:6d} {v.max_dist:9.1e} {v.iterations:7.1f} {dt:5.1f}s")
            if v.wrong:
                log(f"    e.g. {v.example}")
        else:
            log(f"{name:36} ERROR {err}")
        sys.stdout.flush()
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rays", type=int, default=600, help="rays per class (about)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--only", nargs="*", help="class names or prefixes")
    ap.add_argument("--list", action="store_true", help="list the classes and exit")
    args = ap.parse_args(argv)
    names = list(CLASSES)
    if args.list:
        print("\n".join(names))
        return 0
    if args.only:
        names = [k for k in names if any(k.startswith(p) for p in args.only)]
    print(HEADER)
    rows = run_all(names, args.rays, args.seed)
    bad = [r for r in rows if r[1] is None or r[1].wrong]
    print(f"\n{len(rows)} classes, {len(bad)} with wrong rays or errors: "
          + ", ".join(r[0] for r in bad))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
