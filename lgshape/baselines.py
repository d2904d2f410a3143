"""Baseline ray marchers on the same rays and backend, for the benchmark.

- :func:`sphere_trace`: sphere tracing (Hart 1996) with a valid *global*
  Lipschitz bound L of f over the box (from interval arithmetic): step
  |F| / (L |d|); a hit where that distance bound drops below ``eps``. With
  ``relax`` > 1, the over-relaxed variant (Keinert et al. 2014): try
  ``relax`` times the step and fall back to the plain step where the two
  unbounding spheres do not overlap.
- :func:`march`: fixed-step marching with bisection refinement of the first
  sign change; features thinner than the step can be missed, which is the
  seed's point.

Both return a :class:`lgshape.trace.RayResult` (``unresolved`` unused) and
count one evaluation per step. :func:`frozen` runs either as a frozen
function, as :meth:`lgshape.Surface.trace` runs the search (the benchmark
times every method so: no call pays for tracing its Python code again).
"""
from __future__ import annotations

import math

from .arraymath import DrJitMath
from .expr import evaluate
from .grid import clip_to_box
from .trace import FREEZE_LIMIT, RayResult, _rays, call_frozen


def _setup(surface, o, d, t_min, t_max):
    o, d, _ = _rays(o, d, t_min, t_max, True)
    Float = type(o.x)
    t0, t1 = clip_to_box(o, d, [float(v) for v in surface.lo], [float(v) for v in surface.hi],
                         t_min, t_max)
    m = DrJitMath(Float, native=True)     # a baseline's fastest: no error bounds here

    def F(t):
        return evaluate(surface.expr, {"x": o.x + t * d.x, "y": o.y + t * d.y, "z": o.z + t * d.z}, m)
    return o, d, Float, t0, t1, F


def sphere_trace(surface, o, d, L: float, relax: float = 1.0, eps: float | None = None,
                 max_steps: int = 1024, t_min=0.0, t_max=math.inf) -> RayResult:
    import drjit as dr
    o, d, Float, t0, t1, F = _setup(surface, o, d, t_min, t_max)
    UInt32 = dr.uint32_array_t(Float)
    Bool = dr.mask_t(Float)
    n = dr.width(t0)
    eps = 1e-5 * surface.diagonal if eps is None else eps
    inv_L = 1.0 / (L * dr.norm(d))                 # distance bound in units of t
    active = (t0 <= t1) & dr.isfinite(t0)
    f0 = F(t0)

    def body(active, t, r, prev_step, hit, steps):
        # r: distance bound at t. Try the (relaxed) step, fall back if the
        # unbounding spheres of t and t + step do not overlap.
        step = relax * r
        r_try = dr.abs(F(t + step)) * inv_L
        ok = (r + r_try >= step) | (relax == 1.0)
        step = dr.select(ok, step, r)
        t_new = t + step
        r_new = dr.select(ok, r_try, dr.abs(F(t_new)) * inv_L) if relax != 1.0 else r_try
        steps = steps + dr.select(active, 1 if relax == 1.0 else dr.select(ok, 1, 2), 0)
        t = dr.select(active, t_new, t)
        r = dr.select(active, r_new, r)
        done_hit = active & (r < eps) & (t <= t1)
        hit = hit | done_hit
        active = active & ~done_hit & (t <= t1) & (steps < max_steps)
        return active, t, r, step, hit, steps

    state = (Bool(active), Float(t0), dr.abs(f0) * inv_L, dr.zeros(Float, n), dr.zeros(Bool, n),
             dr.zeros(UInt32, n) + 1)
    active, t, r, _, hit, steps = dr.while_loop(state=state, cond=lambda a, *_: a, body=body,
                                                label="sphere_trace")
    hit = hit | ((r < eps) & (t0 <= t1) & (t <= t1))
    capped = (steps >= max_steps) & ~hit
    return RayResult(dr.select(hit, t, math.inf), hit, steps, steps, capped, dr.zeros(Bool, n))


def frozen(method, surface, **settings):
    """``method`` (:func:`sphere_trace` or :func:`march`) for one surface and
    its settings as a frozen function (``dr.freeze``) of (o, d, t_max): a
    call after the first for the same ray count launches the recorded
    kernels. o, d: Dr.Jit arrays; t_max: a Dr.Jit array or a scalar."""
    import drjit as dr

    def run(o, d, t_max, n):     # n, the ray count, keys the recordings
        return method(surface, o, d, t_max=t_max, **settings)
    fn = dr.freeze(run, limit=FREEZE_LIMIT, warn_after=2**30)

    def call(o, d, t_max=math.inf):
        return call_frozen(fn, o, d, t_max, max(dr.width(o), dr.width(d)))
    return call


def march(surface, o, d, step: float, bisections: int = 24, t_min=0.0, t_max=math.inf) -> RayResult:
    """Fixed steps of ``step`` (in units of |d| = 1 lengths) from the box
    entry; the first sign change is refined by bisection."""
    import drjit as dr
    o, d, Float, t0, t1, F = _setup(surface, o, d, t_min, t_max)
    UInt32 = dr.uint32_array_t(Float)
    Bool = dr.mask_t(Float)
    n = dr.width(t0)
    dt = step / dr.norm(d)
    active = (t0 <= t1) & dr.isfinite(t0)

    # Every ray ends: a step below ulp(t) would stall, so a ray that makes no
    # progress is capped (reported as a miss, counted in ``capped``).
    def body(active, a, fa, found, evals, stalled):
        b = dr.minimum(a + dt, t1)
        fb = F(b)
        change = active & (dr.sign(fa) != dr.sign(fb))
        found = found | change
        evals = evals + dr.select(active, 1, 0)
        last = b >= t1
        stalled = stalled | (active & ~change & ~last & (b <= a))
        a = dr.select(active & ~change, b, a)
        fa = dr.select(active & ~change, fb, fa)
        active = active & ~change & ~last & ~stalled
        return active, a, fa, found, evals, stalled

    state = (Bool(active), Float(t0), F(t0), dr.zeros(Bool, n), dr.zeros(UInt32, n) + 1,
             dr.zeros(Bool, n))
    _, a, fa, found, evals, stalled = dr.while_loop(state=state, cond=lambda a, *_: a,
                                                    body=body, label="march")
    lo, hi = Float(a), dr.minimum(a + dt, t1)
    for _ in range(bisections):
        mid = 0.5 * (lo + hi)
        fm = F(mid)
        left = dr.sign(fm) != dr.sign(fa)
        hi = dr.select(left, mid, hi)
        lo = dr.select(left, lo, mid)
        fa = dr.select(left, fa, fm)
    evals = evals + dr.select(found, bisections, 0)
    t = dr.select(found, 0.5 * (lo + hi), math.inf)
    return RayResult(t, found, evals, evals, stalled, dr.zeros(Bool, n))
