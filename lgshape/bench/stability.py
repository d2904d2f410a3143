"""The stability suite: rays built so that ray-surface methods fail.

Part of the benchmark (:mod:`lgshape.bench`), beside the primary-ray
timings. Each :class:`Case` is a surface, a set of rays (float32, as every
method receives them), a ``t_min`` and the float64 answer for every ray: the
nearest root beyond ``t_min`` (``inf`` where there is none), from an oracle
independent of the Dr.Jit kernels (:func:`nearest_root`: exact polynomial
roots for algebraic f, dense float64 sampling otherwise). :func:`judge`
compares a method's answer with it:

- *missed*: the reference has a root and the method reports none, or one
  more than ``TOLERANCE`` (a fraction of the box diagonal) beyond it;
- *false hit*: the method reports a hit where the reference has no root, or
  one more than ``TOLERANCE`` in front of the nearest root;
- *tangent* rays, where either answer is right, are listed per case and
  left out of both counts (they still count for NaNs and the iteration cap).
  A ray is tangent when it was built to touch the surface (a tangent line,
  a line through a singular point) and the reference finds no simple root
  before the touching point, or when the reference has a root within a
  factor 2 of ``t_min`` (float32 rounding of the origin decides there).

The cases (:func:`cases`) come in two groups (:data:`GROUPS`):

- *thin features, tangents and singular points*: needle-thin spikes, rays
  grazing silhouettes, tangent rays, rays through and beside singular points
  (a cone apex, the nodes of Kummer's quartic), a steep wall, origins on the
  surface and a very thin shell;
- *domain and scale*: f scaled by 1e-30 to 1e30, fast-growing f (exp(50 x),
  x^200), partly undefined f (a sqrt height field, a pole, a log domain edge,
  a sign change across an undefined gap), signed-distance primitives built
  with min / max / abs / sqrt (box, rounded box, capsule, capped cylinder,
  smooth unions), spheres far from the origin, degenerate rays (zero,
  infinite or NaN direction, NaN or infinite origin), and many primitives
  on the table path (a written-out union of 16 spheres and 16 rounded boxes
  1e4 and 1e6 from the origin; one of 16 rounded boxes and 16 tori about
  the origin with rays grazing it, parallel to the boxes' faces). Their
  oracles are closed-form wherever one exists (ray / plane, sphere, slab,
  cylinder, the union of those pieces for a capsule or a rounded box, a
  torus's quartic, and for a union the first boundary point of its parts'
  intervals), otherwise a float64 scan whose step is given with the case.

A case may judge lgshape on its float64 ``t64`` (:attr:`Case.judge_t64`)
where the float32 t cannot carry the tolerance (its ulp(t) / 2 is larger):
the verdict is then about the search, and the case says so. Only numpy here;
the bench runs the methods.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..expr import evaluate, gradient, hessian, parse, var
from ..expr.node import exp, log, maximum, minimum, sqrt
from ..reference import (clip_to_box, nearest_root, numpy_f, polynomial_roots,  # noqa: F401
                         rod_intervals)
from .common import DEGREE, DOMAIN, FEATURES, GROUPS, TOLERANCE, Rays, timed  # noqa: F401
from ..surfaces import SPIKE_AXES, Implicit, kummer, sphere, spikes, torus



@dataclass
class Case:
    """Rays against one surface with their float64 answers."""
    name: str
    description: str
    surface: Implicit
    o: np.ndarray            # (n, 3) float32 origins
    d: np.ndarray            # (n, 3) float32 unit directions
    t_min: float
    t_ref: np.ndarray        # (n,) float64 nearest root beyond t_min, inf where none
    tangent: np.ndarray      # (n,) bool: either answer is right
    oracle: str
    group: str = FEATURES
    judge_t64: bool = False  # lgshape judged on its float64 t64 (the search)
    lipschitz: float | None = None  # a known valid L for sphere tracing (exact SDFs: 1)
    scene: object = None     # the table cases' primitives (:class:`TableScene`)

    @property
    def diagonal(self) -> float:
        lo, hi = (np.asarray(v, np.float64) for v in self.surface.bbox)
        return float(np.linalg.norm(hi - lo))


def judge(case: Case, t, hit, normals=None) -> dict:
    """Missed hits, false hits, NaNs of one method's answer on a case (see
    the module text); ``normals`` (n, 3) at the hits, if the method has them."""
    t = np.asarray(t, np.float64)
    hit = np.asarray(hit, bool)
    tol = TOLERANCE * case.diagonal
    judged = ~case.tangent
    has = np.isfinite(case.t_ref)
    t_hit = np.where(hit, t, np.inf)
    missed = judged & has & (~hit | (t_hit > case.t_ref + tol))
    false = judged & hit & (~has | (t_hit < case.t_ref - tol))
    nans = np.isnan(t)
    if normals is not None:
        nans |= hit & np.isnan(np.asarray(normals, np.float64)).any(1)
    return {"missed": int(missed.sum()), "false_hits": int(false.sum()), "nans": int(nans.sum()),
            "tangent": int(case.tangent.sum()), "rays": len(t)}


def run(cases, runners, log):
    """The stability records, and a note per case (its group, description
    and oracle): ``runners(case, rays)`` gives the methods' runner makers for
    a case (the accuracy section's, one setting each). Cases with
    ``judge_t64`` judge lgshape on its float64 t64 (the others have only
    their float32 t)."""
    out, notes = [], []
    for case in cases:
        notes.append({"case": case.name, "group": case.group, "description": case.description,
                      "oracle": case.oracle, "rays": len(case.o),
                      "tangent": int(case.tangent.sum()), "t_min": case.t_min,
                      "judge_t64": case.judge_t64})
        rays = Rays(case.o, case.d, case.t_min)
        for make in runners(case, rays):
            runner = make()
            res, _ = timed(runner, 0)
            on64 = case.judge_t64 and "t64" in res
            t = np.where(res["hit"], res["t64"] if on64 else res["t"], np.inf)
            verdict = judge(case, t, res["hit"], runner.normals(t))
            capped = None if res["capped"] is None else int(res["capped"].sum())
            out.append({"case": case.name, "group": case.group, "method": runner.method,
                        "setting": runner.setting, "missed": verdict["missed"],
                        "false_hits": verdict["false_hits"], "capped": capped,
                        "nans": verdict["nans"], "tangent_excluded": verdict["tangent"],
                        "rays": verdict["rays"], "judged_on": "t64" if on64 else "t",
                        **{k: v for k, v in runner.extra.items() if k in ("lipschitz_L", "note")}})
        log(f"stability {case.name}: " + ", ".join(
            f"{r['method']}[{r['setting']}] {r['missed']}/{r['false_hits']}/{r['capped']}"
            for r in out if r["case"] == case.name))
    return out, notes


# ---- Building the cases ----------------------------------------------------

def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _perpendicular(n, rng):
    """A random unit vector perpendicular to each row of n."""
    return _unit(np.cross(n, rng.normal(size=n.shape)))


def _f32(v):
    return np.ascontiguousarray(v, np.float32)


def _make(name, description, spec, o, d, t_min=0.0, degree=None, steps=4096, t_max=None,
          touching=None, t_touch=None, oracle=None):
    """A Case with its reference. ``touching`` marks rays built to touch the
    surface at parameter ``t_touch``: they are tangent unless the reference
    finds a root clearly before that point."""
    o, d = _f32(o), _f32(_unit(np.asarray(d, np.float64)))
    t_ref = nearest_root(spec, o, d, t_min, degree=degree, steps=steps, t_max=t_max)
    lo, hi = (np.asarray(v, np.float64) for v in spec.bbox)
    diag = float(np.linalg.norm(hi - lo))
    tangent = np.zeros(len(o), bool)
    if touching is not None:
        tangent |= touching & ~(t_ref < np.asarray(t_touch) - TOLERANCE * diag)
    if t_min > 0:
        tangent |= (t_ref >= 0.5 * t_min) & (t_ref <= 2.0 * t_min)
    if oracle is None:
        oracle = (f"float64 roots of the degree-{degree} polynomial F(t)" if degree else
                  f"float64 scan of F(t) at {steps} steps per ray, bisected")
    return Case(name, description, spec, o, d, float(t_min), t_ref, tangent, oracle)


def _torus_points(rng, n, R=1.0, r=0.4):
    """Points on the library torus and their unit normals, in closed form."""
    u, v = rng.uniform(0, 2 * np.pi, (2, n))
    c = np.stack([np.cos(u), np.sin(u), np.zeros(n)], 1)
    nrm = np.cos(v)[:, None] * c + np.sin(v)[:, None] * np.array([0.0, 0.0, 1.0])
    return R * c + r * nrm, nrm


def thin_spikes(rng, n=3):
    spec = spikes()
    o, d = [], []
    for axis in SPIKE_AXES:
        a = _unit(np.asarray(axis, np.float64))
        for sign in (1, -1):
            for h in (0.6, 0.75, 0.9, 1.0):
                u = _perpendicular(np.tile(a, (n, 1)), rng)
                o.append(sign * h * a + 2.0 * u)
                d.append(-u)
    # Every ray crosses a spike axis at t = 2, where f < 0: a scan up to
    # there at a step of 5e-5, far below the spikes' widths, finds the root.
    return _make("thin_spikes", "rays across the 14 needle spikes (about 1e-2 wide) of the "
                 "library 'spikes' surface, perpendicular to a spike at 0.6 to 1.0 of the "
                 "centre distance (the tips are at 1.118)", spec, np.concatenate(o),
                 np.concatenate(d), steps=40000, t_max=2.0,
                 oracle="float64 scan of F(t) up to the spike axis (t = 2, where f < 0), "
                        "step 5e-5, bisected")


def grazing(rng, n=60):
    spec = torus()
    p, nrm = _torus_points(rng, n)
    d = _perpendicular(nrm, rng)
    o, dd = [], []
    for delta in (1e-2, 1e-3, 1e-4):
        for s in (1, -1):
            o.append(p + s * delta * nrm - 3.0 * d)
            dd.append(d)
    return _make("grazing", "rays tangent to the torus at random points, moved off the surface "
                 "by 1e-2, 1e-3 and 1e-4 along the normal, outward (near misses) and inward "
                 "(shallow crossings)", spec, np.concatenate(o), np.concatenate(dd), degree=4)


def tangent(rng, n=120):
    spec = torus()
    p, nrm = _torus_points(rng, n)
    d = _perpendicular(nrm, rng)
    # Plus the lines along the top and bottom circles' tangent planes.
    extra_o = np.array([[-3.0, 0.0, 0.4], [-3.0, 0.0, -0.4], [0.0, -3.0, 0.4], [1.4, -3.0, 0.0]])
    extra_d = np.array([[1.0, 0, 0], [1.0, 0, 0], [0, 1.0, 0], [0, 1.0, 0]])
    o = np.concatenate([p - 3.0 * d, extra_o])
    d = np.concatenate([d, extra_d])
    t_touch = np.concatenate([np.full(n, 3.0), [2.0, 2.0, 2.0, 3.0]])
    return _make("tangent", "lines tangent to the torus (random points and directions, and the "
                 "planes z = +-r and x = R + r); either answer is right unless a simple root "
                 "comes first", spec, o, d, degree=4, touching=np.ones(len(o), bool),
                 t_touch=t_touch)


def _through_and_beside(rng, points, n_dir, offsets):
    """Rays through each point (touching) and passing at the given offsets."""
    o, d, touching = [], [], []
    for q in points:
        dirs = _unit(rng.normal(size=(n_dir, 3)))
        o.append(q - 3.0 * dirs)
        d.append(dirs)
        touching.append(np.ones(n_dir, bool))
        for delta in offsets:
            side = _perpendicular(dirs, rng)
            o.append(q + delta * side - 3.0 * dirs)
            d.append(dirs)
            touching.append(np.zeros(n_dir, bool))
    return np.concatenate(o), np.concatenate(d), np.concatenate(touching)


def singular_cone(rng, n=100):
    spec = Implicit("cone", parse("x^2 + y^2 - z^2"), ((-1.0,) * 3, (1.0,) * 3))
    o, d, touching = _through_and_beside(rng, np.zeros((1, 3)), n, (1e-2, 1e-3, 1e-4))
    return _make("singular_cone", "the cone x^2 + y^2 - z^2 (grad f = 0 at its apex): rays "
                 "through the apex (touching: tangent unless a simple root comes first) and "
                 "passing 1e-2, 1e-3, 1e-4 beside it", spec, o, d, degree=2,
                 touching=touching, t_touch=np.full(len(o), 3.0))


def kummer_nodes(spec, rng, n=20000):
    """The nodes of a surface (f = 0 and grad f = 0): Newton on grad f from
    the samples where |grad f| + |f| is smallest, kept where both vanish."""
    lo, hi = (np.asarray(v, np.float64) for v in spec.bbox)
    g, H = gradient(spec.expr), hessian(spec.expr)

    def stack(exprs, p):
        vals = evaluate(list(exprs), dict(zip("xyz", p.T)))
        return np.stack([np.broadcast_to(v, len(p)) for v in vals], -1).astype(np.float64)
    p = lo + (hi - lo) * rng.uniform(0, 1, (n, 3))
    score = np.linalg.norm(stack(g, p), axis=1) + np.abs(evaluate(spec.expr, dict(zip("xyz", p.T))))
    p = p[np.argsort(score)[:400]]
    for _ in range(40):
        Hv = np.stack([stack(row, p) for row in H], 1)
        p = p - np.linalg.solve(Hv + 1e-12 * np.eye(3), stack(g, p)[..., None])[..., 0]
    fv = evaluate(spec.expr, dict(zip("xyz", p.T)))
    ok = ((np.abs(fv) < 1e-9) & (np.linalg.norm(stack(g, p), axis=1) < 1e-9)
          & np.all((p > lo) & (p < hi), axis=1))
    return np.unique(np.round(p[ok], 9), axis=0)


def singular_kummer(rng, n=16):
    spec = kummer()
    nodes = kummer_nodes(spec, rng)
    o, d, touching = _through_and_beside(rng, nodes, n, (1e-2, 1e-3))
    return _make("singular_kummer", f"Kummer's quartic: rays through its {len(nodes)} nodes "
                 "(grad f = 0; touching: tangent unless a simple root comes first) and passing "
                 "1e-2, 1e-3 beside them", spec, o, d, degree=4, touching=touching,
                 t_touch=np.full(len(o), 3.0))


def steep_wall(rng, n=300, k=1e-3):
    # f = u / sqrt(u^2 + k^2): the sign of u = 0, a wavy wall, but |grad f| up
    # to 1/k = 1000 times |grad u| at the wall while |f| <= 1 everywhere.
    u = "(x - 0.1 + 0.2 * sin(2 * y) * cos(2 * z))"
    spec = Implicit("steep_wall", parse(f"{u} / sqrt({u}^2 + {k * k!r})"),
                    ((-1.0,) * 3, (1.0,) * 3))
    o = 3.0 * _unit(rng.normal(size=(n, 3)))
    aim = rng.uniform(-1, 1, (n, 3))
    return _make("steep_wall", f"a wavy wall u = 0 as f = u / sqrt(u^2 + k^2), k = {k:g}: "
                 "|f| <= 1, but its Lipschitz constant is 1000 times that of u (global bounds "
                 "are tiny steps everywhere)", spec, o, aim - o, steps=8192)


def origin_on_surface(rng, n=100):
    spec = torus()
    p, nrm = _torus_points(rng, n)
    tang = _perpendicular(nrm, rng)
    o = np.concatenate([p, p, p])
    d = np.concatenate([-nrm, nrm, tang])
    diag = float(np.linalg.norm(np.subtract(spec.bbox[1], spec.bbox[0])))
    return _make("origin_on_surface", "rays leaving points of the torus (rounded to float32) "
                 "inward, outward and along the surface, with t_min = 1e-3 diagonals (the "
                 "usual self-intersection offset)", spec, o, d, t_min=1e-3 * diag, degree=4)


def thin_shell(rng, n=300, eps=1e-4):
    spec = Implicit("thin_shell", parse(f"(x^2 + y^2 + z^2 - 1)^2 - {eps * eps!r}"),
                    ((-1.2,) * 3, (1.2,) * 3))
    o = 3.0 * _unit(rng.normal(size=(n, 3)))
    aim = _unit(rng.normal(size=(n, 3))) * rng.uniform(0, 1.05, (n, 1)) ** (1 / 3)
    return _make("thin_shell", f"the shell (|p|^2 - 1)^2 = {eps:g}^2, about {eps:g} thick, hit "
                 "from random directions (some rays miss the ball)", spec, o, aim - o, degree=4)


# ---- Domain and scale: closed-form oracles ----------------------------------

def _ray_ball(o, d, c, r):
    """Entry and exit t of the ball |p - c| <= r along o + t d (float64;
    NaN where the line misses it). From the closest approach, so that far
    origins lose no precision to cancellation."""
    oc = o - np.asarray(c, np.float64)
    dd = np.sum(d * d, 1)
    tc = -np.sum(oc * d, 1) / dd
    m = oc + tc[:, None] * d
    disc = r * r - np.sum(m * m, 1)
    with np.errstate(invalid="ignore"):
        h = np.sqrt(disc / dd)
    return np.where(disc >= 0, tc - h, np.nan), np.where(disc >= 0, tc + h, np.nan)


def _ray_slab(o, d, lo, hi):
    """Entry and exit t of the box [lo, hi] (NaN where the line misses it)."""
    tn, tf = clip_to_box(o, d, np.asarray(lo, np.float64), np.asarray(hi, np.float64),
                         t_min=-np.inf)
    ok = tn <= tf
    return np.where(ok, tn, np.nan), np.where(ok, tf, np.nan)


def _ray_rod(o, d, a, b, r):
    """Entry and exit t of the solid cylinder of radius r around the segment
    a-b, capped flat at a and b (NaN where the line misses it)."""
    a, b = (np.asarray(v, np.float64).reshape(1, 3) for v in (a, b))
    tn, tf = rod_intervals(o, d, a, b, np.array([float(r)]))
    return tn[:, 0], tf[:, 0]


def _union(pieces):
    """Entry and exit of a convex union of convex pieces: the line meets the
    union in one interval, the hull of the pieces' intervals."""
    tn = np.stack([p[0] for p in pieces], 1)
    tf = np.stack([p[1] for p in pieces], 1)
    tn = np.where(np.isnan(tn), np.inf, tn).min(1)
    tf = np.where(np.isnan(tf), -np.inf, tf).max(1)
    ok = tn <= tf
    return np.where(ok, tn, np.nan), np.where(ok, tf, np.nan)


def _first_root(spec, o, d, t_min, roots):
    """The nearest of the candidate roots (n, k) in the box beyond t_min."""
    lo, hi = (np.asarray(v, np.float64) for v in spec.bbox)
    t0, t1 = clip_to_box(o, d, lo, hi, t_min=t_min)
    r = np.asarray(roots, np.float64)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(r) & (r >= t0[:, None]) & (r <= t1[:, None])
    return np.where(ok, r, np.inf).min(1)


def _convex_root(spec, o, d, t_min, interval):
    """The nearest boundary point of a convex solid: its entry, or its exit
    from inside (the entry and exit being the line's only roots)."""
    tn, tf = interval
    tn = np.where(tn < tf, tn, np.nan)             # a tangent line touches: no crossing
    return _first_root(spec, o, d, t_min, np.stack([tn, tf], 1))


def _plane_oracle(spec, *xs):
    """The first root among the planes x = xs along each ray (float64)."""
    return lambda o, d: _first_root(spec, o, d, 0.0, _plane_roots(o, d, 0, list(xs)))


def _plane_roots(o, d, axis, values):
    """t where o + t d meets the planes x_axis = v (inf where parallel)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = [(v - o[:, axis]) / d[:, axis] for v in values]
    return np.where(np.isfinite(t), t, np.inf).T


def _domain_case(name, description, spec, o, d, oracle, t_ref_fn, t_min=0.0, tangent=None,
                 **kw):
    """A domain-and-scale Case: rays rounded to float32 first, then the
    oracle ``t_ref_fn(o64, d64)`` on exactly those rays."""
    o, d = _f32(o), _f32(_unit(np.asarray(d, np.float64)))
    t_ref = t_ref_fn(o.astype(np.float64), d.astype(np.float64))
    tangent = np.zeros(len(o), bool) if tangent is None else tangent
    return Case(name, description, spec, o, d, float(t_min), t_ref, tangent, oracle,
                group=DOMAIN, **kw)


def _camera(rng, n, lo, hi, radius=None, centre=None):
    """Rays from points around the box aimed at uniform points inside it."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    c = 0.5 * (lo + hi) if centre is None else np.asarray(centre, np.float64)
    radius = 1.5 * float(np.linalg.norm(hi - lo)) if radius is None else radius
    o = c + radius * _unit(rng.normal(size=(n, 3)))
    aim = lo + (hi - lo) * rng.uniform(0, 1, (n, 3))
    return o, aim - o


def _near_tangent(rng, p, nrm, offsets=(1e-2, 1e-3, 1e-4), back=3.0):
    """Rays along random tangents at surface points p (unit normals nrm),
    moved off by each offset outward (near misses) and inward (shallow
    crossings), starting ``back`` before the point."""
    d = _perpendicular(nrm, rng)
    o = [p + s * delta * nrm - back * d for delta in offsets for s in (1, -1)]
    return np.concatenate(o), np.tile(d, (2 * len(offsets), 1))


def _sphere_points(rng, n, c=(0.0, 0.0, 0.0), r=1.0):
    nrm = _unit(rng.normal(size=(n, 3)))
    return np.asarray(c, np.float64) + r * nrm, nrm


# -- scaled f --

SCALES = (1e-30, 1e-12, 1e12, 1e30)


def _scaled(shape, k):
    def build(rng, n):
        base = sphere() if shape == "sphere" else torus()
        spec = Implicit(f"scaled_{shape}", k * base.expr, base.bbox)
        p, nrm = (_sphere_points(rng, n) if shape == "sphere" else _torus_points(rng, n))
        og, dg = _near_tangent(rng, p, nrm, offsets=(1e-3, 1e-4))
        oc, dc = _camera(rng, 2 * n, *base.bbox)
        deg = DEGREE[shape]
        return _domain_case(
            f"scaled_{shape}_{k:g}", f"k f for the library {shape}, k = {k:g}: rays from "
            f"around its box and near-tangent rays (offsets 1e-3, 1e-4); the roots are those of "
            f"f for every k (the hits of k f must not depend on k)", spec,
            np.concatenate([oc, og]), np.concatenate([dc, dg]),
            f"float64 roots of the unscaled degree-{deg} polynomial",
            lambda o, d: nearest_root(base, o, d, degree=deg))
    build.__name__ = f"scaled_{shape}_{k:g}"
    return build


# -- fast-growing f --

def _plane_rays(rng, n, spec, axis, value, angles=(1e-2, 1e-3)):
    """Camera rays, and rays crossing the plane x_axis = value at shallow
    angles (long stretches where |F| is small) near the box middle."""
    lo, hi = (np.asarray(v, np.float64) for v in spec.bbox)
    oc, dc = _camera(rng, 2 * n, lo, hi)
    o, d = [oc], [dc]
    others = [i for i in range(3) if i != axis]
    for a in angles:
        p = lo + (hi - lo) * rng.uniform(0.3, 0.7, (n, 3))
        p[:, axis] = value
        t = np.zeros((n, 3))
        phi = rng.uniform(0, 2 * np.pi, n)
        t[:, others[0]], t[:, others[1]] = np.cos(phi), np.sin(phi)
        e = np.zeros(3)
        e[axis] = 1.0
        s = rng.choice([-1.0, 1.0], n)[:, None]
        dd = math.cos(a) * t + s * math.sin(a) * e
        o.append(p - 0.5 * dd)
        d.append(dd)
    return np.concatenate(o), np.concatenate(d)


def exp_wall(rng, n=100):
    x0 = math.log(2.0) / 50.0
    spec = Implicit("exp_wall", parse("exp(50 * x) - 2"), ((-1.0,) * 3, (1.0,) * 3))
    o, d = _plane_rays(rng, n, spec, 0, x0)
    return _domain_case(
        "exp_wall", "exp(50 x) - 2 in [-1, 1]^3 (f from -2 to 5e21, |grad f| up to 3e23, all "
        "within float32): the plane x = ln 2 / 50; rays from around the box and rays crossing "
        "the plane at 1e-2 and 1e-3 rad", spec, o, d,
        "ray / plane x = ln(2) / 50 in float64",
        _plane_oracle(spec, x0))


def pow200(rng, n=100):
    x0 = 0.5 ** (1 / 200)
    spec = Implicit("pow200", parse("x^200 - 0.5"), ((-1.25,) * 3, (1.25,) * 3))
    o, d = _plane_rays(rng, n, spec, 0, x0)
    return _domain_case(
        "pow200", "x^200 - 0.5 in [-1.25, 1.25]^3 (f, its derivative and its second "
        "derivative, up to 6e23, within float32; f is flat at -0.5 over most of the box): the "
        "planes x = +-0.5^(1/200); rays from around the box and rays crossing x = 0.5^(1/200) "
        "at 1e-2 and 1e-3 rad", spec, o, d,
        "ray / planes x = +-0.5^(1/200) in float64",
        _plane_oracle(spec, x0, -x0))


# -- partly undefined f --

def hemisphere(rng, n=100):
    spec = Implicit("hemisphere", parse("z - sqrt(1 - x^2 - y^2)"),
                    ((-1.2, -1.2, -0.6), (1.2, 1.2, 1.2)))
    oc, dc = _camera(rng, 3 * n, *spec.bbox)
    # Rim rays: horizontal lines through the disc just above the rim (they
    # cross the steep edge of the height field) and just below it (f < 0
    # inside the cylinder, undefined outside: no root at all).
    o, d = [oc], [dc]
    for zoff in (1e-2, 1e-3, -1e-3, -1e-2):
        phi = rng.uniform(0, 2 * np.pi, n)
        dd = np.stack([np.cos(phi), np.sin(phi), np.zeros(n)], 1)
        side = np.stack([-np.sin(phi), np.cos(phi), np.zeros(n)], 1)
        p = side * rng.uniform(-0.95, 0.95, (n, 1)) + np.array([0.0, 0.0, zoff])
        o.append(p - 2.0 * dd)
        d.append(dd)

    def oracle(o, d):
        t0, t1 = _ray_ball(o, d, (0.0, 0.0, 0.0), 1.0)
        r = np.stack([t0, t1], 1)
        with np.errstate(invalid="ignore"):
            z = o[:, 2, None] + r * d[:, 2, None]
            r = np.where(z >= 0, r, np.nan)
        return _first_root(spec, o, d, 0.0, r)
    return _domain_case(
        "hemisphere", "the height field z = sqrt(1 - x^2 - y^2) as f = z - sqrt(1 - x^2 - y^2), "
        "undefined outside the unit cylinder (box [-1.2, 1.2]^2 x [-0.6, 1.2]): rays from "
        "around the box, and horizontal rays through the disc 1e-2 and 1e-3 above the rim "
        "(steep crossings) and below it (f < 0 meets undefined: no root)", spec,
        np.concatenate(o), np.concatenate(d), "unit-sphere roots with z >= 0 (closed form, "
        "float64)", oracle)


def _x_rays(rng, n, spec, spread=0.3):
    """Camera rays, and rays mostly along +x and -x starting outside the box."""
    lo, hi = (np.asarray(v, np.float64) for v in spec.bbox)
    oc, dc = _camera(rng, 2 * n, lo, hi)
    o, d = [oc], [dc]
    for s in (1.0, -1.0):
        dd = _unit(np.column_stack([np.full(n, s), spread * rng.normal(size=(n, 2))]))
        start = lo + (hi - lo) * rng.uniform(0.1, 0.9, (n, 3))
        start[:, 0] = lo[0] - 0.1 if s > 0 else hi[0] + 0.1
        o.append(start)
        d.append(dd)
    return np.concatenate(o), np.concatenate(d)


def inverse_pole(rng, n=100):
    spec = Implicit("inverse_pole", parse("1 / x - 2"), ((-1.0,) * 3, (1.0,) * 3))
    o, d = _x_rays(rng, n, spec)
    return _domain_case(
        "inverse_pole", "1 / x - 2 in [-1, 1]^3: the plane x = 0.5 is the only root; at the "
        "pole x = 0, f jumps from -inf to +inf (a sign change that is not a root); rays from "
        "around the box and along +-x, many crossing the pole, some leaving the box before "
        "x = 0.5", spec, o, d, "ray / plane x = 0.5 in float64 (the pole excluded)",
        _plane_oracle(spec, 0.5))


def log_edge(rng, n=100):
    x0 = math.exp(0.5) - 1.5
    spec = Implicit("log_edge", parse("log(x + 1.5) - 0.5"), ((-2.0, -1.0, -1.0), (1.0, 1.0, 1.0)))
    o, d = _x_rays(rng, n, spec)
    return _domain_case(
        "log_edge", "log(x + 1.5) - 0.5 in [-2, 1] x [-1, 1]^2: undefined for x < -1.5, "
        "-inf at the edge of its domain; the plane x = e^0.5 - 1.5; rays from around the box "
        "and along +-x, those along +x starting in the undefined part", spec, o, d,
        "ray / plane x = e^0.5 - 1.5 in float64",
        _plane_oracle(spec, x0))


def undefined_gap(rng, n=100):
    spec = Implicit("undefined_gap", parse("x * (x - 0.6) / sqrt(x^2 - 0.04)"),
                    ((-1.0,) * 3, (1.0,) * 3))
    o, d = _x_rays(rng, n, spec)
    return _domain_case(
        "undefined_gap", "x (x - 0.6) / sqrt(x^2 - 0.04) in [-1, 1]^3: undefined for |x| < "
        "0.2, +inf at x = -0.2 and -inf at x = 0.2, so f changes sign across the gap, which "
        "is not a root; the plane x = 0.6 is; rays from around the box and along +-x", spec,
        o, d, "ray / plane x = 0.6 in float64 (the gap excluded)",
        _plane_oracle(spec, 0.6))


# -- signed-distance primitives --

X, Y, Z = var("x"), var("y"), var("z")


def _sd_box(px, py, pz, b):
    """Inigo Quilez's exact box SDF: |max(q, 0)| + min(max(q), 0), q = |p| - b."""
    q = [abs(px) - b[0], abs(py) - b[1], abs(pz) - b[2]]
    outside = sqrt(sum((maximum(qi, 0.0) ** 2 for qi in q[1:]), maximum(q[0], 0.0) ** 2))
    return outside + minimum(maximum(*q), 0.0)


SDF_BOX = (0.6, 0.4, 0.3)          # half extents
SDF_ROUND = 0.1                    # rounding radius of the rounded box
CAPSULE = ((-0.5, -0.2, 0.1), (0.5, 0.3, -0.1), 0.25)
CYLINDER = (0.5, 0.6)              # radius, half height (axis z)
SDF_BBOX = ((-1.0,) * 3, (1.0,) * 3)


def _box_points(rng, n, b):
    """Points on the faces of the box [-b, b] with their normals."""
    axis = rng.integers(0, 3, n)
    sign = rng.choice([-1.0, 1.0], n)
    b = np.asarray(b, np.float64)
    p = rng.uniform(-1, 1, (n, 3)) * b
    p[np.arange(n), axis] = sign * b[axis]
    nrm = np.zeros((n, 3))
    nrm[np.arange(n), axis] = sign
    return p, nrm


def _sdf_case(name, description, spec, rng, n, p, nrm, interval_fn, oracle):
    oc, dc = _camera(rng, 2 * n, *spec.bbox)
    og, dg = _near_tangent(rng, p, nrm)
    return _domain_case(
        name, description + "; rays from around the box aimed inside it, and near-tangent "
        "rays (random tangents at surface points, moved off by 1e-2, 1e-3, 1e-4 outward and "
        "inward); sphere tracing gets L = 1 (an exact SDF; interval arithmetic bounds |grad f| "
        "by inf here)", spec, np.concatenate([oc, og]), np.concatenate([dc, dg]), oracle,
        lambda o, d: _convex_root(spec, o, d, 0.0, interval_fn(o, d)), lipschitz=1.0)


def sdf_box(rng, n=50):
    b = SDF_BOX
    spec = Implicit("sdf_box", _sd_box(X, Y, Z, b), SDF_BBOX)
    p, nrm = _box_points(rng, n, b)
    return _sdf_case("sdf_box", f"the exact box SDF (abs, max, min, sqrt of max(q, 0)^2), half "
                     f"extents {b}", spec, rng, n, p, nrm,
                     lambda o, d: _ray_slab(o, d, -np.asarray(b), b),
                     "slab test (closed form, float64)")


def _round_box_pieces(b, r):
    e = np.asarray(b, np.float64) - r              # the inner box
    pieces = []
    for i in range(3):
        g = e.copy()
        g[i] += r
        pieces.append(("slab", -g, g))
    for i in range(3):
        j, k = [a for a in range(3) if a != i]
        for sj in (-1, 1):
            for sk in (-1, 1):
                a, b_ = np.zeros(3), np.zeros(3)
                a[i], b_[i] = -e[i], e[i]
                a[j] = b_[j] = sj * e[j]
                a[k] = b_[k] = sk * e[k]
                pieces.append(("rod", a, b_))
    for s in np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).T.reshape(-1, 3):
        pieces.append(("ball", s * e, None))
    return pieces


def sdf_round_box(rng, n=50):
    b, r = SDF_BOX, SDF_ROUND
    e = np.asarray(b) - r
    expr = _sd_box(X, Y, Z, tuple(e)) - r
    spec = Implicit("sdf_round_box", expr, SDF_BBOX)
    pieces = _round_box_pieces(b, r)
    # Surface points: on the flat faces, and on the corner balls.
    p1, n1 = _box_points(rng, n - n // 3, e)
    p1 = p1 + r * n1
    n2 = _unit(np.abs(rng.normal(size=(n // 3, 3)))) * rng.choice([-1.0, 1.0], (n // 3, 3))
    p2 = np.sign(n2) * e + r * n2

    def interval(o, d):
        out = []
        for kind, a, c in pieces:
            if kind == "slab":
                out.append(_ray_slab(o, d, a, c))
            elif kind == "rod":
                out.append(_ray_rod(o, d, a, c, r))
            else:
                out.append(_ray_ball(o, d, a, r))
        return _union(out)
    return _sdf_case("sdf_round_box", f"the rounded box SDF (the box SDF of half extents "
                     f"{tuple(round(float(v), 3) for v in e)} minus {r}), so the box {b} with edges "
                     f"rounded by {r}", spec, rng, n, np.concatenate([p1, p2]),
                     np.concatenate([n1, n2]), interval,
                     "closed form, float64: the union of 3 slabs, 12 edge cylinders and 8 "
                     "corner balls (the rounded box is exactly that union)")


def sdf_capsule(rng, n=50):
    a, b, r = CAPSULE
    a_, b_ = np.asarray(a), np.asarray(b)
    ba = b_ - a_
    pa = [X - a[0], Y - a[1], Z - a[2]]
    h = minimum(maximum((pa[0] * ba[0] + pa[1] * ba[1] + pa[2] * ba[2]) / float(ba @ ba), 0.0),
                1.0)
    q = [pa[i] - float(ba[i]) * h for i in range(3)]
    spec = Implicit("sdf_capsule", sqrt(q[0] ** 2 + q[1] ** 2 + q[2] ** 2) - r, SDF_BBOX)
    # Surface points: the side (normal perpendicular to the axis) and the caps.
    u = ba / np.linalg.norm(ba)
    ns = _perpendicular(np.tile(u, (n - n // 3, 1)), rng)
    ps = a_ + rng.uniform(0, 1, (n - n // 3, 1)) * ba + r * ns
    nc = _unit(rng.normal(size=(n // 3, 3)))
    end = np.where((nc @ u)[:, None] > 0, b_, a_)
    pc = end + r * nc
    return _sdf_case("sdf_capsule", f"the capsule SDF (a clamp by min / max, sqrt) of the "
                     f"segment {a}-{b}, radius {r}", spec, rng, n, np.concatenate([ps, pc]),
                     np.concatenate([ns, nc]),
                     lambda o, d: _union([_ray_rod(o, d, a, b, r), _ray_ball(o, d, a, r),
                                          _ray_ball(o, d, b, r)]),
                     "closed form, float64: ray / finite cylinder and ray / the two end balls")


def sdf_cylinder(rng, n=50):
    r, hh = CYLINDER
    dx, dz = sqrt(X ** 2 + Y ** 2) - r, abs(Z) - hh
    expr = minimum(maximum(dx, dz), 0.0) + sqrt(maximum(dx, 0.0) ** 2 + maximum(dz, 0.0) ** 2)
    spec = Implicit("sdf_cylinder", expr, SDF_BBOX)
    m = n - n // 3
    phi = rng.uniform(0, 2 * np.pi, n)
    ns = np.stack([np.cos(phi[:m]), np.sin(phi[:m]), np.zeros(m)], 1)
    ps = r * ns + np.column_stack([np.zeros((m, 2)), rng.uniform(-hh, hh, m)])
    k = n - m
    rho = r * np.sqrt(rng.uniform(0, 1, k))
    sz = rng.choice([-1.0, 1.0], k)
    pc = np.stack([rho * np.cos(phi[m:]), rho * np.sin(phi[m:]), sz * hh], 1)
    nc = np.column_stack([np.zeros((k, 2)), sz])
    return _sdf_case("sdf_cylinder", f"the capped cylinder SDF (sqrt, abs, min, max) around "
                     f"the z axis, radius {r}, half height {hh}", spec, rng, n,
                     np.concatenate([ps, pc]), np.concatenate([ns, nc]),
                     lambda o, d: _ray_rod(o, d, (0, 0, -hh), (0, 0, hh), r),
                     "closed form, float64: ray / infinite cylinder intersected with the slab "
                     "|z| <= h")


SMOOTH_BALLS = (((-0.35, 0.0, 0.0), 0.45), ((0.4, 0.1, 0.0), 0.35))


def _smooth(kind, k):
    (c1, r1), (c2, r2) = SMOOTH_BALLS
    a = sqrt((X - c1[0]) ** 2 + (Y - c1[1]) ** 2 + (Z - c1[2]) ** 2) - r1
    b = sqrt((X - c2[0]) ** 2 + (Y - c2[1]) ** 2 + (Z - c2[2]) ** 2) - r2
    if kind == "poly":
        h = minimum(maximum(0.5 + 0.5 * (b - a) / k, 0.0), 1.0)
        return b + h * (a - b) - k * h * (1.0 - h)
    return -k * log(exp(-a / k) + exp(-b / k))


def _smooth_case(kind, k, steps=8192):
    def build(rng, n):
        name = f"sdf_smooth_union_{kind}"
        spec = Implicit(name, _smooth(kind, k), SDF_BBOX)
        (c1, r1), (c2, r2) = SMOOTH_BALLS
        o, d = _camera(rng, 3 * n, (-0.85, -0.5, -0.5), (0.8, 0.5, 0.5), radius=3.0,
                       centre=(0.0, 0.0, 0.0))
        form = ("the polynomial smin (h = clamp(1/2 + (b - a) / 2k, 0, 1), mix(b, a, h) - "
                f"k h (1 - h), k = {k:g})" if kind == "poly" else
                f"the log-sum-exp smin (-k log(e^(-a/k) + e^(-b/k)), k = {k:g})")
        diag = 2 * math.sqrt(3)
        return _domain_case(
            name, f"the smooth union by {form} of the ball SDFs a, b (centres {c1}, {c2}, "
            f"radii {r1}, {r2}); rays from a distance of 3 aimed at the blend's box; sphere "
            f"tracing gets L = 1 (|grad f| <= 1 for both smin forms of two exact SDFs)", spec, o,
            d, f"float64 scan of F(t) at {steps} steps over the ray's part of the box (a step of "
            f"at most diag / {steps} = {diag / steps:.1e}), bisected (no closed form)",
            lambda o, d: nearest_root(spec, o, d, steps=steps), lipschitz=1.0)
    build.__name__ = f"sdf_smooth_union_{kind}"
    return build


# -- far from the origin --

FAR = ((1e4, 1e4, 1e4), 1.0)
FAR_SMALL = ((1e4, -1e4, 1e4), 1e-3)


def _far_spec(name, c, r):
    return Implicit(name, (X - c[0]) ** 2 + (Y - c[1]) ** 2 + (Z - c[2]) ** 2 - r * r,
                    (tuple(v - 1.1 * r for v in c), tuple(v + 1.1 * r for v in c)))


def _ball_oracle(spec, c, r):
    return lambda o, d: _convex_root(spec, o, d, 0.0, _ray_ball(o, d, c, r))


def far_sphere(rng, n=100):
    c, r = FAR
    spec = _far_spec("far_sphere", c, r)
    lo, hi = spec.bbox
    # A camera at the world origin (t about 1.7e4), and near-tangent rays
    # from 3 radii away.
    oc = np.zeros((2 * n, 3))
    dc = np.asarray(lo) + (np.asarray(hi) - np.asarray(lo)) * rng.uniform(0, 1, (2 * n, 3))
    p, nrm = _sphere_points(rng, n, c, r)
    og, dg = _near_tangent(rng, p, nrm, offsets=(1e-2, 1e-3))
    return _domain_case(
        "far_sphere", "the unit sphere centred at (1e4, 1e4, 1e4) in its tight box (1.1 "
        "radii): rays from a camera at the world origin (t ~ 1.7e4: ulp(t) / 2 ~ 1e-3 is 3e-4 "
        "diagonals) and near-tangent rays (offsets 1e-2, 1e-3 before the float32 rounding of "
        "their origins, whose ulp there is 1e-3); lgshape judged on its float64 t64",
        spec, np.concatenate([oc, og]), np.concatenate([dc, dg]),
        "ray / sphere in float64 from the float32 rays (closest-approach form)",
        _ball_oracle(spec, c, r), judge_t64=True)


def _far_small_rays(rng, n, c, r, origin, pool=40):
    """Rays aimed at the small sphere; candidates from a pool so that about
    half hit (float32 directions are coarse at this distance)."""
    spec = _far_spec("far_small_sphere", c, r)
    lo, hi = (np.asarray(v, np.float64) for v in spec.bbox)
    m = pool * n
    if origin is None:
        o = np.asarray(c) + 0.01 * _unit(rng.normal(size=(m, 3)))
    else:
        o = np.tile(np.asarray(origin, np.float64), (m, 1))
    aim = np.asarray(c) + r * 1.05 * _unit(rng.normal(size=(m, 3))) \
        * rng.uniform(0, 1, (m, 1)) ** (1 / 3)
    o32, d32 = _f32(o), _f32(_unit(aim - o))
    t = _ball_oracle(spec, c, r)(o32.astype(np.float64), d32.astype(np.float64))
    hit = np.flatnonzero(np.isfinite(t))[: (2 * n + 1) // 2]
    miss = np.flatnonzero(~np.isfinite(t))[: 2 * n - len(hit)]
    keep = np.concatenate([hit, miss])
    return spec, o32[keep], d32[keep]


def far_small_sphere(rng, n=100):
    c, r = FAR_SMALL
    spec, o, d = _far_small_rays(rng, n, c, r, None)
    return _domain_case(
        "far_small_sphere", "a sphere of radius 1e-3 centred at (1e4, -1e4, 1e4), where "
        "float32 positions are 1e-3 apart, in its tight box (diagonal 3.8e-3): rays from "
        "0.01 away (t ~ 1e-2, so ulp(t) is negligible), about half of them hitting; lgshape "
        "judged on its float64 t64", spec, o, d,
        "ray / sphere in float64 from the float32 rays (closest-approach form)",
        _ball_oracle(spec, c, r), judge_t64=True)


def far_small_sphere_origin(rng, n=100):
    c, r = FAR_SMALL
    spec, o, d = _far_small_rays(rng, n, c, r, (0.0, 0.0, 0.0))
    return _domain_case(
        "far_small_sphere_origin", "the same sphere (radius 1e-3 at (1e4, -1e4, 1e4)) seen "
        "from a camera at the world origin: t ~ 1.7e4, whose float32 ulp / 2 (1e-3) is 26 "
        "times the tolerance (3.8e-5), so no float32 t can be judged right; lgshape is judged "
        "on its float64 t64 (the search), the other methods on their float32 t; march's "
        "step (diag / 256 = 1.5e-5) is below ulp(t) = 2e-3, so t + step == t: its rays "
        "stall and are capped", spec, o, d,
        "ray / sphere in float64 from the float32 rays (closest-approach form)",
        _ball_oracle(spec, c, r), judge_t64=True)


# -- degenerate rays --

def degenerate_rays(rng, n=None):
    spec = sphere()
    inf, nan = np.inf, np.nan
    rows = [  # (origin, direction)
        ((0.5, 0.0, 0.0), (0.0, 0.0, 0.0)), ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
        ((1.0, 0.0, 0.0), (0.0, 0.0, 0.0)), ((0.0, 0.6, 0.8), (0.0, 0.0, 0.0)),
        ((-3.0, 0.0, 0.0), (inf, 0.0, 0.0)), ((-3.0, 0.0, 0.0), (inf, 1.0, 0.0)),
        ((0.0, 0.0, 0.0), (1.0, -inf, 0.0)), ((0.0, -3.0, 0.0), (-inf, inf, 0.0)),
        ((-3.0, 0.0, 0.0), (nan, 0.0, 0.0)), ((-3.0, 0.0, 0.0), (1.0, nan, 0.0)),
        ((0.0, 0.0, 0.0), (nan, nan, nan)), ((0.5, 0.0, 0.0), (0.0, 0.0, nan)),
        ((nan, 0.0, 0.0), (1.0, 0.0, 0.0)), ((0.0, nan, -3.0), (0.0, 0.0, 1.0)),
        ((nan, nan, nan), (0.0, 0.0, 1.0)), ((0.0, 0.0, nan), (0.0, 0.0, 1.0)),
        ((-inf, 0.0, 0.0), (1.0, 0.0, 0.0)), ((0.0, inf, 0.0), (0.0, -1.0, 0.0)),
        ((-inf, -inf, -inf), (1.0, 1.0, 1.0)), ((inf, 0.0, 0.0), (nan, 0.0, 0.0)),
    ]
    o = _f32([r[0] for r in rows])
    d = _f32([r[1] for r in rows])
    return Case("degenerate_rays", "the unit sphere and rays that are no rays: zero "
                "directions (origins inside the box, two on the surface), directions with an "
                "infinite or NaN component, NaN and infinite origins; every one is a miss "
                "and must end (capped rays counted)", spec, o, d, 0.0,
                np.full(len(o), np.inf), np.zeros(len(o), bool),
                "none needed: every ray is a miss (the contract)", group=DOMAIN)


# -- many primitives: the table path ----------------------------------------

@dataclass
class TableScene:
    """Primitives as float64 rows: spheres (c, r), capsules (a, b, r),
    boxes (c, half sizes h, rounding; 0: sharp), tori (c, R, r) about z
    (any of them may be empty)."""
    spheres: np.ndarray
    capsules: np.ndarray
    boxes: np.ndarray
    tori: np.ndarray

    def expr(self):
        """The union min_i d_i written out (exact distances, one structure
        per kind: rounded and sharp boxes apart), which
        :func:`lgshape.tables.find_tables` turns into tables (16 operands or
        more of one structure)."""
        terms = []
        for cx, cy, cz, r in self.spheres:
            terms.append(sqrt((X - cx) ** 2 + (Y - cy) ** 2 + (Z - cz) ** 2) - r)
        for row in self.capsules:
            a, b, r = row[:3], row[3:6], row[6]
            ba = b - a
            p = [X - a[0], Y - a[1], Z - a[2]]
            h = minimum(maximum((p[0] * ba[0] + p[1] * ba[1] + p[2] * ba[2])
                                * (1.0 / float(ba @ ba)), 0.0), 1.0)
            terms.append(sqrt(sum((p[i] - ba[i] * h) ** 2 for i in range(3))) - r)
        for row in self.boxes:
            c, hh, r = row[:3], row[3:6], row[6]
            e = _sd_box(X - c[0], Y - c[1], Z - c[2], tuple(hh - r))
            terms.append(e - r if r > 0 else e)
        for cx, cy, cz, R, r in self.tori:
            terms.append(sqrt((sqrt((X - cx) ** 2 + (Y - cy) ** 2) - R) ** 2 + (Z - cz) ** 2) - r)
        return minimum(*terms)

    def bbox(self, pad=0.05):
        lo = np.concatenate([self.spheres[:, :3] - self.spheres[:, 3:4],
                             np.minimum(self.capsules[:, :3], self.capsules[:, 3:6])
                             - self.capsules[:, 6:7],
                             self.boxes[:, :3] - self.boxes[:, 3:6],
                             self.tori[:, :3] - np.column_stack([self.tori[:, 3] + self.tori[:, 4]] * 2
                                                                + [self.tori[:, 4]])]).min(0)
        hi = np.concatenate([self.spheres[:, :3] + self.spheres[:, 3:4],
                             np.maximum(self.capsules[:, :3], self.capsules[:, 3:6])
                             + self.capsules[:, 6:7],
                             self.boxes[:, :3] + self.boxes[:, 3:6],
                             self.tori[:, :3] + np.column_stack([self.tori[:, 3] + self.tori[:, 4]] * 2
                                                                + [self.tori[:, 4]])]).max(0)
        m = pad * float((hi - lo).max())
        return tuple(map(float, lo - m)), tuple(map(float, hi + m))

    def intervals(self, o, d):
        """(entry, exit) of every primitive's solid along the rays, closed
        forms in float64: balls; capsules as ray / finite cylinder and its
        end balls; rounded boxes as 3 slabs, 12 edge cylinders and 8 corner
        balls; sharp boxes as slabs; tori from their quartic's real roots
        (float64 polynomial roots, paired in order)."""
        out = []
        for cx, cy, cz, r in self.spheres:
            out.append(_ray_ball(o, d, (cx, cy, cz), r))
        for row in self.capsules:
            a, b, r = row[:3], row[3:6], row[6]
            out.append(_union([_ray_rod(o, d, a, b, r), _ray_ball(o, d, a, r), _ray_ball(o, d, b, r)]))
        for row in self.boxes:
            c, hh, r = row[:3], row[3:6], row[6]
            if r == 0:
                out.append(_ray_slab(o, d, c - hh, c + hh))
                continue
            pieces = []
            for kind, a, b in _round_box_pieces(hh, r):
                if kind == "slab":
                    pieces.append(_ray_slab(o, d, c + a, c + b))
                elif kind == "rod":
                    pieces.append(_ray_rod(o, d, c + a, c + b, r))
                else:
                    pieces.append(_ray_ball(o, d, c + a, r))
            out.append(_union(pieces))
        for cx, cy, cz, R, r in self.tori:
            e = _torus_quartic((cx, cy, cz), R, r)
            c = np.array([cx, cy, cz])
            # the quartic about the ray's closest approach to the centre
            tc = -np.sum((o - c) * d, 1) / np.sum(d * d, 1)
            w = (R + r) * 1.01
            rt = polynomial_roots(numpy_f(e), 4, o, d, tc - 2 * w, tc + 2 * w)
            real = np.abs(rt.imag) <= 1e-9 * w
            t = np.sort(np.where(real, rt.real, np.nan), 1)
            cnt = np.isfinite(t).sum(1)
            t = np.where((cnt % 2 == 0)[:, None], t, np.nan)
            out += [(t[:, 0], t[:, 1]), (t[:, 2], t[:, 3])]
        return out


def _torus_quartic(c, R, r):
    px, py, pz = X - c[0], Y - c[1], Z - c[2]
    q = px ** 2 + py ** 2
    return (q + pz ** 2 + (R * R - r * r)) ** 2 - 4 * R * R * q


def _union_roots(intervals, t0, t1):
    """The boundary points of the union of the intervals in (t0, t1), (n, k)
    sorted, inf padded: the roots of min_i d_i."""
    tn = np.stack([i[0] for i in intervals], 1)
    tf = np.stack([i[1] for i in intervals], 1)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(tn) & np.isfinite(tf) & (tf >= tn)
        a, b = t0[:, None], t1[:, None]
        start = (ok & (tn <= a) & (tf > a)).sum(1)
        enter, leave = ok & (tn > a) & (tn < b), ok & (tf > a) & (tf < b)
    ev = np.concatenate([np.where(enter, tn, np.inf), np.where(leave, tf, np.inf)], 1)
    mk = np.concatenate([enter.astype(int), -leave.astype(int)], 1)
    order = np.lexsort((-mk, ev), axis=1)
    ev, mk = np.take_along_axis(ev, order, 1), np.take_along_axis(mk, order, 1)
    cum = start[:, None] + np.cumsum(mk, 1)
    root = (mk != 0) & ((cum - mk == 0) != (cum == 0))
    return np.sort(np.where(root, ev, np.inf), 1)


def _table_scene(rng, centre, kinds=("sphere", "box"), n=16, size=1.0):
    """n primitives of each of ``kinds`` (spheres, rounded boxes, tori: one
    table each) in the cube centre +- size; values float32 (as a scene's).
    No remainder outside the tables: its constants would be the kernel's
    literals, compiled anew for every case; and few kinds, since the
    benchmark's "taylor" and seed runners compile the whole expression."""
    c = np.asarray(centre, np.float64)

    def at(k):
        return c + size * rng.uniform(-0.8, 0.8, (k, 3))

    def f32(v):
        return np.asarray(v, np.float32).astype(np.float64).reshape(-1, v.shape[1])
    sph, rb, tor = np.zeros((0, 4)), np.zeros((0, 7)), np.zeros((0, 5))
    if "sphere" in kinds:
        sph = np.column_stack([at(n), size * rng.uniform(0.06, 0.15, n)])
    if "box" in kinds:
        h = size * rng.uniform(0.05, 0.15, (n, 3))
        rb = np.column_stack([at(n), h, h.min(1) * rng.uniform(0.2, 0.9, n)])
    if "torus" in kinds:
        R = size * rng.uniform(0.12, 0.2, n)
        tor = np.column_stack([at(n), R, R * rng.uniform(0.2, 0.35, n)])
    return TableScene(f32(sph), np.zeros((0, 7)), f32(rb), f32(tor))


def _table_points(scene: TableScene, rng, n):
    """Points on the spheres, the flat parts of the rounded boxes' faces and
    the tori (closed forms) with their normals."""
    kinds = [k for k, rows in (("sphere", scene.spheres), ("box", scene.boxes),
                               ("torus", scene.tori)) if len(rows)]
    k = rng.integers(0, len(kinds), n)
    p, nrm = np.zeros((n, 3)), np.zeros((n, 3))
    for j, kind in enumerate(kinds):
        i = np.flatnonzero(k == j)
        if kind == "sphere":
            s = scene.spheres[rng.integers(0, len(scene.spheres), len(i))]
            nrm[i] = _unit(rng.normal(size=(len(i), 3)))
            p[i] = s[:, :3] + s[:, 3:4] * nrm[i]
        elif kind == "box":
            b = scene.boxes[rng.integers(0, len(scene.boxes), len(i))]
            q, nq = _box_points(rng, len(i), (1.0, 1.0, 1.0))
            p[i] = b[:, :3] + q * (b[:, 3:6] - b[:, 6:7]) + nq * b[:, 6:7]
            nrm[i] = nq
        else:
            t = scene.tori[rng.integers(0, len(scene.tori), len(i))]
            u, v = rng.uniform(0, 2 * np.pi, (2, len(i)))
            ring = np.stack([np.cos(u), np.sin(u), np.zeros(len(i))], 1)
            nrm[i] = np.cos(v)[:, None] * ring + np.sin(v)[:, None] * np.array([0.0, 0.0, 1.0])
            p[i] = t[:, :3] + t[:, 3:4] * ring + t[:, 4:5] * nrm[i]
    return p, nrm


def _table_case(name, description, scene: TableScene, o, d, judge_t64=False):
    spec = Implicit(name, scene.expr(), scene.bbox())
    lo, hi = (np.asarray(v, np.float64) for v in spec.bbox)
    diag = float(np.linalg.norm(hi - lo))

    def oracle(o64, d64):
        t0, t1 = clip_to_box(o64, d64, lo, hi)
        r = _union_roots(scene.intervals(o64, d64), t0, np.maximum(t0, t1))
        return r
    o32, d32 = _f32(o), _f32(_unit(np.asarray(d, np.float64)))
    roots = oracle(o32.astype(np.float64), d32.astype(np.float64))
    t_ref = roots[:, 0]
    # either answer is right where the first root is a touch: the next root
    # within twice the search's smallest interval (2e-6 diagonals)
    with np.errstate(invalid="ignore"):
        tangent = np.isfinite(t_ref) & (roots[:, 1] - t_ref < 2e-6 * diag) if roots.shape[1] > 1 \
            else np.zeros(len(t_ref), bool)
    return Case(name, description, spec, o32, d32, 0.0, t_ref, tangent,
                "closed form, float64: the union of every primitive's ray interval (ray / "
                "sphere; capsule: ray / finite cylinder and end balls; rounded box: 3 slabs, 12 "
                "edge cylinders, 8 corner balls; sharp box: slabs; torus: the quartic's float64 "
                "roots), its first boundary point", group=DOMAIN, judge_t64=judge_t64,
                lipschitz=1.0, scene=scene)


def _table_far(off):
    def build(rng, n):
        c = (off, -off, off / 2)
        scene = _table_scene(rng, c)
        lo, hi = scene.bbox()
        oc, dc = _camera(rng, 2 * n, lo, hi)
        p, nrm = _table_points(scene, rng, n)
        og, dg = _near_tangent(rng, p, nrm, offsets=(1e-2, 1e-3), back=1.0)
        return _table_case(
            f"table_far_{off:g}", f"a union written out as min(...) of 32 exact distances (16 "
            f"spheres, 16 rounded boxes: two tables) in a cube of half size 1 centred at ({off:g}, {-off:g}, {off / 2:g}): rays from "
            f"around it and near-tangent rays at sphere and box-face points (offsets "
            f"1e-2, 1e-3, before the float32 rounding of the origins, whose ulp is "
            f"{float(np.spacing(np.float32(off))):g} here); the table path, each template's "
            f"offsets about the table's centre", scene, np.concatenate([oc, og]),
            np.concatenate([dc, dg]))
    build.__name__ = f"table_far_{off:g}"
    return build


def table_grazing_mixed(rng, n=60):
    scene = _table_scene(rng, (0.0, 0.0, 0.0), ("box", "torus"))
    spec_f = numpy_f(scene.expr())
    p, nrm = _table_points(scene, rng, 8 * n)
    on = np.abs(spec_f(*p.T)) < 1e-9          # on the union's surface (not inside another part)
    p, nrm = p[on][:n], nrm[on][:n]
    o, d = _near_tangent(rng, p, nrm, offsets=(1e-2, 1e-4, 1e-6), back=1.0)
    return _table_case(
        "table_grazing_mixed", "a union written out as min(...) of 16 rounded boxes and 16 tori "
        "(two tables) about the origin: rays along random tangents at points of the union's "
        "surface (flat parts of the boxes' faces: directions parallel to a face; tori), moved "
        "off by 1e-2, 1e-4, 1e-6 outward (near misses; along a face F is tiny over a long "
        "stretch) and "
        "inward (shallow crossings)", scene, o, d)


#: The case builders with their default ray counts (per spike, or per case).
BUILDERS = ((thin_spikes, 3), (grazing, 60), (tangent, 120), (singular_cone, 100),
            (singular_kummer, 16), (steep_wall, 300), (origin_on_surface, 100), (thin_shell, 300))

#: Offsets of the far table cases from the origin.
TABLE_OFFSETS = (1e4, 1e6)

#: The domain-and-scale builders (ray counts: per camera / tangent set, see each).
DOMAIN_BUILDERS = (
    *((_scaled(shape, k), 40) for shape in ("sphere", "torus") for k in SCALES),
    (exp_wall, 60), (pow200, 60),
    (hemisphere, 60), (inverse_pole, 60), (log_edge, 60), (undefined_gap, 60),
    (sdf_box, 30), (sdf_round_box, 30), (sdf_capsule, 30), (sdf_cylinder, 30),
    (_smooth_case("poly", 0.3), 60), (_smooth_case("lse", 0.1), 60),
    (far_sphere, 60), (far_small_sphere, 60), (far_small_sphere_origin, 60),
    (degenerate_rays, 1),
    *((_table_far(off), 30) for off in TABLE_OFFSETS), (table_grazing_mixed, 40))


def cases(seed: int = 5, scale: float = 1.0, groups=GROUPS) -> list[Case]:
    """All cases, reproducibly; ``scale`` < 1 takes fewer rays per case;
    ``groups``: which of :data:`GROUPS`."""
    out = []
    for group, builders, base in ((FEATURES, BUILDERS, 0), (DOMAIN, DOMAIN_BUILDERS, 1000)):
        if group not in groups:
            continue
        out += [build(np.random.default_rng([seed, base + i]), max(1, int(math.ceil(n * scale))))
                for i, (build, n) in enumerate(builders)]
    return out
