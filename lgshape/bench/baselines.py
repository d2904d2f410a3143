"""The methods the benchmark sets against lgshape, on the same rays and
backend, and their runners (:class:`lgshape.bench.common.Runner`).

Ray marchers, on Dr.Jit arrays:

- :func:`sphere_trace`: sphere tracing (Hart 1996) with a valid *global*
  Lipschitz bound L of f over the box (from interval arithmetic): step
  |F| / (L |d|); a hit where that distance bound drops below ``eps``. With
  ``relax`` > 1, the over-relaxed variant (Keinert et al. 2014): try
  ``relax`` times the step and fall back to the plain step where the two
  unbounding spheres do not overlap.
- :func:`march`: fixed-step marching with bisection refinement of the first
  sign change; features thinner than the step can be missed.

Both return a :class:`lgshape.trace.RayResult` (``unresolved`` unused) and
count one evaluation per step. :func:`frozen` runs either as a frozen
function, as :meth:`lgshape.Surface.trace` runs the search (the benchmark
times every method so: no call pays for tracing its Python code again);
:func:`sphere_runner` and :func:`march_runner` are their runners.

Grid methods, fed f / |grad f| sampled on a grid over the box
(:func:`sample_grid`, :class:`Samples`): Mitsuba's native ``sdfgrid``
(:func:`sdfgrid_runner`) and scikit-image's marching-cubes mesh of the same
samples traced by Embree (:func:`mesh_runner`).

Dr.Jit, Mitsuba and scikit-image (the ``bench`` extra) are imported where
they are used.
"""
from __future__ import annotations

import math
import time

import numpy as np

from ..arraymath import DrJitMath
from ..expr import evaluate, gradient
from ..grid import clip_to_box
from ..trace import FREEZE_LIMIT, RayResult, call_frozen, check_rays
from .common import Runner, empty_runner, f_normals, global_L, mitsuba_mesh, plain_surface, \
    read_ray_result


# ---- Ray marchers -------------------------------------------------------------------

def _setup(surface, o, d, t_min, t_max):
    o, d, _ = check_rays(o, d, t_min, t_max, True)
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


# ---- Their runners ------------------------------------------------------------------

def sphere_runner(spec, rays, eps, relax, L=None):
    """Sphere tracing to ``eps`` box diagonals, over-relaxed by ``relax``
    (1: plain); ``L``: a known valid Lipschitz bound (else interval
    arithmetic's)."""
    t0 = time.perf_counter()
    surf = plain_surface(spec)
    L = global_L(spec) if L is None else L
    build = time.perf_counter() - t0
    st = frozen(sphere_trace, surf, L=L, relax=relax, eps=eps * surf.diagonal, t_min=rays.t_min)

    def run():
        r = st(rays.o_dr, rays.d_dr)
        return r.t, r.hit, r.evals, r.capped
    method = "sphere_trace" if relax == 1.0 else "sphere_trace_relaxed"
    return Runner(method, f"eps {eps:g} diag", run, read_ray_result, f_normals(surf, rays),
                  0, build, {"lipschitz_L": L, "relax": relax})


def march_runner(spec, rays, divisions):
    """Marching in steps of 1 / ``divisions`` of the box diagonal."""
    surf = plain_surface(spec)
    marcher = frozen(march, surf, step=surf.diagonal / divisions, t_min=rays.t_min)

    def run():
        r = marcher(rays.o_dr, rays.d_dr)
        return r.t, r.hit, r.evals, r.capped
    return Runner("march", f"step diag/{divisions}", run, read_ray_result,
                  f_normals(surf, rays), 0, 0.0)


# ---- Grid methods -------------------------------------------------------------------

def sample_grid(spec, res):
    """f / |grad f| (float64; a first-order distance with the signs of f) at
    res^3 vertices spanning the box, indexed [z, y, x]: what sdfgrid and
    marching cubes are fed. Dividing by |grad f| keeps every sign, and so the
    topology the samples see, and halves their depth error against raw f.
    Where grad f vanishes the divisor is floored at 1e-6 of its largest
    finite value; where it is undefined (NaN, e.g. the 0 / 0 of sqrt's
    derivative inside an exact SDF) while f is defined, f is taken as is."""
    lo, hi = (np.asarray(v, np.float64) for v in spec.bbox)
    ax = [np.linspace(lo[i], hi[i], res) for i in range(3)]
    f, gn = np.empty((res, res, res)), np.empty((res, res, res))
    exprs = [spec.expr, *gradient(spec.expr)]
    slab = max(1, 2**17 // (res * res))
    for k in range(0, res, slab):
        Z, Y, X = np.meshgrid(ax[2][k:k + slab], ax[1], ax[0], indexing="ij")
        v = [np.broadcast_to(e, X.shape) for e in evaluate(exprs, {"x": X, "y": Y, "z": Z})]
        f[k:k + slab] = v[0]
        gn[k:k + slab] = np.sqrt(v[1]**2 + v[2]**2 + v[3]**2)
    fin = np.isfinite(gn)
    top = gn[fin].max() if fin.any() else 1.0
    gn = np.where(np.isnan(gn) & np.isfinite(f), 1.0, gn)
    return f / np.maximum(gn, 1e-6 * top + 1e-300)


class Samples:
    """The grid samples of one resolution, taken once for sdfgrid and mesh;
    ``seconds`` (the sampling time) counts in both builds."""

    def __init__(self, spec, res):
        self.spec, self.res, self._f, self.seconds = spec, res, None, 0.0

    @property
    def f(self):
        if self._f is None:
            t0 = time.perf_counter()
            self._f = sample_grid(self.spec, self.res)
            self.seconds = time.perf_counter() - t0
        return self._f


def _mitsuba_runner(method, setting, scene, rays, memory, build, extra=None):
    def run():
        return (scene.ray_intersect_preliminary(rays.ray).t,)

    def read(out):
        t = np.asarray(out[0]).astype(np.float64) + rays.t_min
        return {"t": np.where(np.isfinite(t), t, np.inf), "hit": np.isfinite(t),
                "evals": None, "capped": None}

    def normals(t):
        si = scene.ray_intersect(rays.ray)
        n = np.asarray(si.sh_frame.n).T.astype(np.float64)
        return np.where(np.isfinite(t)[:, None], n, np.nan)
    return Runner(method, setting, run, read, normals, memory, build, extra or {})


def _transform(spec):
    import mitsuba as mi
    lo, hi = (np.asarray(v, np.float64) for v in spec.bbox)
    T = mi.ScalarTransform4f()
    return T.translate(lo.tolist()) @ T.scale((hi - lo).tolist())


def sdfgrid_runner(spec, rays, samples: Samples):
    """Mitsuba's sdfgrid of the samples (no geometry where no voxel has a sign change)."""
    import mitsuba as mi
    f = samples.f
    t0 = time.perf_counter()
    setting = f"{samples.res}^3 samples"
    try:
        scene = mi.load_dict({"type": "scene", "shape": {
            "type": "sdfgrid", "grid": mi.TensorXf(f.astype(np.float32)[..., None]),
            "to_world": _transform(spec)}})
    except RuntimeError as err:             # no voxel with a sign change
        return empty_runner("sdfgrid", setting, rays, samples.seconds, str(err))
    return _mitsuba_runner("sdfgrid", setting, scene, rays, int(f.size * 4),
                           samples.seconds + time.perf_counter() - t0)


def mesh_runner(spec, rays, samples: Samples):
    """The marching-cubes mesh of the samples, traced by Mitsuba."""
    import mitsuba as mi
    from skimage.measure import marching_cubes
    f = samples.f
    t0 = time.perf_counter()
    lo, hi = (np.asarray(v, np.float64) for v in spec.bbox)
    setting = f"{samples.res}^3 samples"
    spacing = tuple((hi - lo)[::-1] / (samples.res - 1))
    try:
        v, faces, _, _ = marching_cubes(f, 0.0, spacing=spacing)
    except (ValueError, RuntimeError) as err:       # no sign change in the samples
        return empty_runner("mesh", setting, rays, samples.seconds, str(err))
    v = v[:, ::-1] + lo                              # [z, y, x] -> (x, y, z)
    scene = mi.load_dict({"type": "scene", "shape": mitsuba_mesh(v, faces)})
    memory = 4 * (2 * v.size + faces.size)           # positions, normals, indices
    return _mitsuba_runner("mesh", setting, scene, rays, int(memory),
                           samples.seconds + time.perf_counter() - t0,
                           {"triangles": int(len(faces))})


def sampling_runners(spec, rays, march_steps, grid_res):
    """The methods that look at f in fixed places, built lazily (each item's
    make() returns a Runner): marching at each of ``march_steps`` (divisions
    of the diagonal), then sdfgrid and the mesh at each of ``grid_res``
    (samples per axis; one :class:`Samples` for both)."""
    for n in march_steps:
        yield lambda n=n: march_runner(spec, rays, n)
    for res in grid_res:
        samples = Samples(spec, res)
        yield lambda samples=samples: sdfgrid_runner(spec, rays, samples)
        yield lambda samples=samples: mesh_runner(spec, rays, samples)
