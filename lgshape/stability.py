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

The cases (:func:`cases`): needle-thin spikes, rays grazing silhouettes,
tangent rays, rays through and beside singular points (a cone apex, the
nodes of Kummer's quartic), a steep wall, origins on the surface and a very
thin shell. Only numpy here; the bench runs the methods.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .expr import evaluate, gradient, hessian, parse
from .reference import clip_to_box, first_sign_change, polynomial_roots
from .surfaces import SPIKE_AXES, Implicit, kummer, spikes, torus

#: Degree of the algebraic library surfaces (their f is a polynomial): the
#: reference for them is exact polynomial roots.
DEGREE = {"sphere": 2, "torus": 4, "tangle": 4, "barth_sextic": 6, "kummer": 4,
          "chmutov6": 6, "clebsch": 3}

#: Depth tolerance of the missed / false-hit verdicts, in box diagonals.
TOLERANCE = 1e-2

#: A complex root counts as real when |Im t| is below this (in diagonals).
REAL_ROOT = 1e-6


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

    @property
    def diagonal(self) -> float:
        lo, hi = (np.asarray(v, np.float64) for v in self.surface.bbox)
        return float(np.linalg.norm(hi - lo))


def numpy_f(expr):
    """f as a float64 numpy callable F(X, Y, Z) (the reference's view of f)."""
    return lambda X, Y, Z: evaluate(expr, {"x": X, "y": Y, "z": Z})


def nearest_root(spec: Implicit, o, d, t_min=0.0, degree=None, steps=4096, t_max=None):
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


def reference_normal(spec: Implicit, p):
    """Unit float64 gradient of f at points p (n, 3); NaN where grad f = 0."""
    g = evaluate(list(gradient(spec.expr)), dict(zip("xyz", np.asarray(p, np.float64).T)))
    g = np.stack([np.broadcast_to(v, len(p)) for v in g], 1).astype(np.float64)
    n = np.linalg.norm(g, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, g / n, np.nan)


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


#: The case builders with their default ray counts (per spike, or per case).
BUILDERS = ((thin_spikes, 3), (grazing, 60), (tangent, 120), (singular_cone, 100),
            (singular_kummer, 16), (steep_wall, 300), (origin_on_surface, 100), (thin_shell, 300))


def cases(seed: int = 5, scale: float = 1.0) -> list[Case]:
    """All cases, reproducibly; ``scale`` < 1 takes fewer rays per case."""
    return [build(np.random.default_rng([seed, i]), max(1, int(math.ceil(n * scale))))
            for i, (build, n) in enumerate(BUILDERS)]
