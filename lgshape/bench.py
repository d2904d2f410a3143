"""The benchmark, ``lgshape bench [--quick] --out DIR``: lgshape against the
usual ways of rendering an implicit surface, speed against accuracy.

For each library surface, the same primary rays (:mod:`lgshape.camera`, one
fixed camera per surface) go through every method and setting on the same
backend (Dr.Jit LLVM, Mitsuba's ``llvm_ad_rgb``):

- ``lgshape``: the guaranteed search with local bounds (search modes
  ``interval`` and ``taylor``, pruning depths); ``lgshape_global``: the
  seed's global constants (one G for the box, with and without the global-L
  pruning);
- ``sphere_trace`` and ``sphere_trace_relaxed`` (over-relaxation 1.6) with
  the valid global Lipschitz bound L of interval arithmetic, at several
  termination thresholds; ``march``: fixed steps with bisection;
- ``sdfgrid``: Mitsuba's native shape, fed f / |grad f| sampled on a grid
  over the box (:func:`sample_grid`; it intersects the zero set of the
  trilinear interpolant of the samples, voxel by voxel);
- ``mesh``: scikit-image's marching cubes of the same samples as a Mitsuba
  mesh (smooth vertex normals from its faces), traced by Embree.

Metrics per record: Mrays/s (the median of timed samples after a warm-up,
rays and acceleration structure already built, see :func:`timed`), function
evaluations per ray (where the method evaluates f), the memory of the
acceleration structure, and, on the same traces (every pixel, or a regular
subset of them), accuracy against a float64 reference (:func:`lgshape.stability.nearest_root`:
polynomial roots for algebraic surfaces, a dense scan otherwise): the
fraction of pixels with a wrong hit or miss, the depth error |t - t_ref| in
box diagonals over the pixels both hit (mean and max), and the mean angle
between the method's normal line and the float64 gradient at the reference
hit (degrees; a NaN normal counts 90). Then the stability suite
(:mod:`lgshape.stability`) on the same methods.

Writes DIR/results.json, DIR/charts/<surface>.png (error against time per
ray, one curve per method), DIR/charts/all.png and DIR/BENCHMARKS.md.
"""
from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import subprocess
import sys
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from . import stability
from .camera import primary_rays
from .surfaces import LIBRARY
from .trace import DEFAULT_DEPTH

VARIANT = "llvm_ad_rgb"


@dataclass(frozen=True)
class Config:
    res: int                       # primary rays: res x res
    stride: int                    # accuracy on every stride-th row and column
    repeats: int                   # timed runs (after one warm-up)
    surfaces: tuple
    depths: tuple                  # lgshape interval-mode pruning depths
    modes: tuple                   # further lgshape settings at the default depth
    st_eps: tuple                  # sphere-tracing thresholds, in box diagonals
    march_steps: tuple             # fixed steps, as divisions of the diagonal
    grid_res: tuple                # sdfgrid / marching-cubes samples per axis
    scan_steps: int                # reference scan for non-algebraic surfaces
    stability_scale: float         # fraction of the stability suite's rays
    stability_grid: int            # sdfgrid / mesh resolution in the suite
    min_sample: float              # seconds per timing sample (repeated traces)


FULL = Config(res=512, stride=2, repeats=5, surfaces=tuple(LIBRARY), depths=(6, 7, 8),
              modes=("taylor", "global", "seed"), st_eps=(1e-3, 1e-4, 1e-5, 1e-6),
              march_steps=(64, 256, 1024), grid_res=(32, 64, 128, 256), scan_steps=8192,
              stability_scale=1.0, stability_grid=128, min_sample=0.1)
QUICK = Config(res=64, stride=1, repeats=3, surfaces=tuple(LIBRARY),
               depths=(DEFAULT_DEPTH,), modes=("seed",), st_eps=(1e-3, 1e-5),
               march_steps=(64, 256),
               grid_res=(32, 64), scan_steps=2048, stability_scale=0.5, stability_grid=64,
               min_sample=0.02)

#: The lgshape setting the headline compares (the library's default).
DEFAULT_LG = f"interval, depth {DEFAULT_DEPTH}"


# ---- Methods ------------------------------------------------------------------

@dataclass
class Runner:
    """One method at one setting, ready to trace prepared rays."""
    method: str
    setting: str
    run: Callable[[], tuple]                # traces; returns Dr.Jit arrays
    read: Callable[[tuple], dict]           # -> numpy t, hit, evals, capped
    normals: Callable[[np.ndarray], np.ndarray]   # normals at hit rays
    memory_bytes: int
    build_s: float
    extra: dict = field(default_factory=dict)


class Rays:
    """The rays of one run, in the forms the methods take (evaluated once,
    so no timed call recompiles or uploads them)."""

    def __init__(self, o, d, t_min=0.0):
        import drjit as dr
        import mitsuba as mi
        from .trace import default_array3f
        Array3f = default_array3f()
        self.o, self.d, self.t_min = np.asarray(o, np.float32), np.asarray(d, np.float32), t_min
        self.o_dr, self.d_dr = Array3f(self.o.T.copy()), Array3f(self.d.T.copy())
        # Mitsuba's rays have no t_min: start them t_min further along (not
        # at all where t_min = 0: 0 * inf would turn an origin into NaN).
        with np.errstate(invalid="ignore", over="ignore"):
            o_off = self.o if t_min == 0 else (self.o + np.float32(t_min) * self.d).astype(np.float32)
        self.ray = mi.Ray3f(mi.Point3f(o_off.T.copy()), mi.Vector3f(self.d.T.copy()))
        dr.eval(self.o_dr, self.d_dr, self.ray)

    def points(self, t, idx):
        return self.o[idx].astype(np.float64) + t[idx, None] * self.d[idx].astype(np.float64)


def _read_ray_result(out):
    t, hit, evals, capped = (np.asarray(v) for v in out[:4])
    res = {"t": t.astype(np.float64), "hit": hit.astype(bool),
           "evals": evals.astype(np.float64), "capped": capped.astype(bool)}
    if len(out) > 4:                    # lgshape's float64 t (RayResult.t64)
        res["t64"] = np.asarray(out[4]).astype(np.float64)
    return res


def _f_normals(surf, rays):
    def normals(t):
        out = np.full((len(t), 3), np.nan)
        idx = np.flatnonzero(np.isfinite(t))
        if len(idx):
            out[idx] = np.asarray(surf.normal(rays.points(t, idx).astype(np.float32))).T
        return out
    return normals


def global_L(spec) -> float:
    """The valid global Lipschitz bound of f over the box (interval arithmetic)."""
    from . import bounds
    lo, hi = (np.asarray(v, np.float64)[None] for v in spec.bbox)
    return float(bounds.lipschitz(spec.expr, lo, hi)[0])


def lgshape_runner(spec, rays, mode, depth, t64=False):
    """``mode``: a search mode, or ``"seed"`` (global L pruning and global G).
    ``t64``: also return the float64 t (for cases judged on it)."""
    import lgshape
    t0 = time.perf_counter()
    if mode == "seed":
        surf = lgshape.Surface(spec, L=global_L(spec), search="global", depth=depth)
        method, setting = "lgshape_global", f"global L and G, depth {depth}"
    else:
        surf = lgshape.Surface(spec, search=mode, depth=depth)
        method = "lgshape_global" if mode == "global" else "lgshape"
        setting = f"{'global G' if mode == 'global' else mode}, depth {depth}"
    build = time.perf_counter() - t0

    def run():
        r = surf.trace(rays.o_dr, rays.d_dr, t_min=rays.t_min)
        return (r.t, r.hit, r.evals, r.capped) + ((r.t64,) if t64 else ())
    return Runner(method, setting, run, _read_ray_result, _f_normals(surf, rays),
                  int(surf.memory_bytes), build)


def _plain_surface(spec):
    """A Surface as the baselines' view of f, its box and its rays (they use
    no pruning grid; the coarsest one keeps the build negligible)."""
    import lgshape
    return lgshape.Surface(spec, depth=2)


def sphere_runner(spec, rays, eps, relax, L=None):
    """``L``: a known valid Lipschitz bound (else interval arithmetic's)."""
    from . import baselines
    t0 = time.perf_counter()
    surf = _plain_surface(spec)
    L = global_L(spec) if L is None else L
    build = time.perf_counter() - t0
    st = baselines.frozen(baselines.sphere_trace, surf, L=L, relax=relax, eps=eps * surf.diagonal,
                          t_min=rays.t_min)

    def run():
        r = st(rays.o_dr, rays.d_dr)
        return r.t, r.hit, r.evals, r.capped
    method = "sphere_trace" if relax == 1.0 else "sphere_trace_relaxed"
    return Runner(method, f"eps {eps:g} diag", run, _read_ray_result, _f_normals(surf, rays),
                  0, build, {"lipschitz_L": L, "relax": relax})


def march_runner(spec, rays, divisions):
    from . import baselines
    surf = _plain_surface(spec)
    march = baselines.frozen(baselines.march, surf, step=surf.diagonal / divisions,
                             t_min=rays.t_min)

    def run():
        r = march(rays.o_dr, rays.d_dr)
        return r.t, r.hit, r.evals, r.capped
    return Runner("march", f"step diag/{divisions}", run, _read_ray_result,
                  _f_normals(surf, rays), 0, 0.0)


def sample_grid(spec, res):
    """f / |grad f| (float64; a first-order distance with the signs of f) at
    res^3 vertices spanning the box, indexed [z, y, x]: what sdfgrid and
    marching cubes are fed. Dividing by |grad f| keeps every sign, and so the
    topology the samples see, and halves their depth error against raw f.
    Where grad f vanishes the divisor is floored at 1e-6 of its largest
    finite value; where it is undefined (NaN, e.g. the 0 / 0 of sqrt's
    derivative inside an exact SDF) while f is defined, f is taken as is."""
    from .expr import evaluate, gradient
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


def _empty_runner(method, setting, rays, build, note, has_cap=False):
    """A method left with no geometry (e.g. no sign change on its grid), or
    refused; ``has_cap``: the method has an iteration cap (no ray reached it)."""
    n = len(rays.o)

    def read(out):
        return {"t": np.full(n, np.inf), "hit": np.zeros(n, bool), "evals": None,
                "capped": np.zeros(n, bool) if has_cap else None}
    return Runner(method, setting, lambda: (), read, lambda t: np.full((n, 3), np.nan), 0, build,
                  {"note": note})


def _transform(spec):
    import mitsuba as mi
    lo, hi = (np.asarray(v, np.float64) for v in spec.bbox)
    T = mi.ScalarTransform4f()
    return T.translate(lo.tolist()) @ T.scale((hi - lo).tolist())


def sdfgrid_runner(spec, rays, samples: Samples):
    import mitsuba as mi
    f = samples.f
    t0 = time.perf_counter()
    setting = f"{samples.res}^3 samples"
    try:
        scene = mi.load_dict({"type": "scene", "shape": {
            "type": "sdfgrid", "grid": mi.TensorXf(f.astype(np.float32)[..., None]),
            "to_world": _transform(spec)}})
    except RuntimeError as err:             # no voxel with a sign change
        return _empty_runner("sdfgrid", setting, rays, samples.seconds, str(err))
    return _mitsuba_runner("sdfgrid", setting, scene, rays, int(f.size * 4),
                           samples.seconds + time.perf_counter() - t0)


def mesh_runner(spec, rays, samples: Samples):
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
        return _empty_runner("mesh", setting, rays, samples.seconds, str(err))
    v = v[:, ::-1] + lo                              # [z, y, x] -> (x, y, z)
    mesh = mi.Mesh("marching_cubes", len(v), len(faces), has_vertex_normals=True)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(v.astype(np.float32).ravel())
    params["faces"] = mi.UInt32(faces.astype(np.uint32).ravel())
    params.update()
    mesh.recompute_vertex_normals()                   # area-weighted face normals
    scene = mi.load_dict({"type": "scene", "shape": mesh})
    memory = 4 * (2 * v.size + faces.size)           # positions, normals, indices
    return _mitsuba_runner("mesh", setting, scene, rays, int(memory),
                           samples.seconds + time.perf_counter() - t0,
                           {"triangles": int(len(faces))})


def runners(spec, rays, cfg: Config):
    """Every method and setting of the primary-ray benchmark, built lazily."""
    for depth in cfg.depths:
        yield lambda depth=depth: lgshape_runner(spec, rays, "interval", depth)
    for mode in cfg.modes:
        yield lambda mode=mode: lgshape_runner(spec, rays, mode, DEFAULT_DEPTH)
    for relax in (1.0, 1.6):
        for eps in cfg.st_eps:
            yield lambda eps=eps, relax=relax: sphere_runner(spec, rays, eps, relax)
    for n in cfg.march_steps:
        yield lambda n=n: march_runner(spec, rays, n)
    for res in cfg.grid_res:
        samples = Samples(spec, res)
        yield lambda samples=samples: sdfgrid_runner(spec, rays, samples)
        yield lambda samples=samples: mesh_runner(spec, rays, samples)


def _seed_runner(spec, rays):
    """The seed's setting, or, where f has no finite global L over its box
    (a pole, a sqrt at the edge of its domain), a record of its refusal: no
    hits, no ray capped, and the reason in ``note``."""
    try:
        return lgshape_runner(spec, rays, "seed", DEFAULT_DEPTH, t64=True)
    except ValueError as err:
        return _empty_runner("lgshape_global", f"global L and G, depth {DEFAULT_DEPTH}", rays, 0.0,
                             f"refused: {err}", has_cap=True)


def stability_runners(spec, rays, cfg: Config, L=None):
    """The methods of the stability suite: one representative setting each
    (``L``: a known Lipschitz bound for sphere tracing, see
    :attr:`stability.Case.lipschitz`)."""
    samples = Samples(spec, cfg.stability_grid)
    yield lambda: lgshape_runner(spec, rays, "interval", DEFAULT_DEPTH, t64=True)
    yield lambda: lgshape_runner(spec, rays, "taylor", DEFAULT_DEPTH, t64=True)
    yield lambda: _seed_runner(spec, rays)
    yield lambda: sphere_runner(spec, rays, 1e-5, 1.0, L)
    yield lambda: sphere_runner(spec, rays, 1e-5, 1.6, L)
    yield lambda: march_runner(spec, rays, 256)
    yield lambda: sdfgrid_runner(spec, rays, samples)
    yield lambda: mesh_runner(spec, rays, samples)


# ---- Measuring ----------------------------------------------------------------

def timed(runner: Runner, repeats: int, min_sample: float = 0.0):
    """Outputs and the time of one trace: the median of ``repeats`` samples
    after a warm-up, each sample running the trace as often as it takes to
    last ``min_sample`` seconds (so that scheduling jitter on shared cores
    averages out); 3 samples where one trace takes over a second. ``repeats``
    = 0: one run, compilation included."""
    if repeats == 0:
        t0 = time.perf_counter()
        out = _run_once(runner)
        return runner.read(out), time.perf_counter() - t0
    res, seconds, _ = timed_together({0: runner}, repeats, min_sample)[0]
    return res, seconds


def _run_once(runner: Runner):
    """One trace, its outputs evaluated and the backend synchronised."""
    import drjit as dr
    out = runner.run()
    dr.eval(*out)
    dr.sync_thread()
    return out


def timed_together(runners: dict, repeats: int, min_sample: float = 0.0):
    """:func:`timed` for several runners on the same rays, their samples
    interleaved: after a warm-up and a calibration of each, round k takes
    one sample of every runner in turn (the order rotating from round to
    round), so that a change of the shared cores' speed during the
    measurement weighs on all of them alike. Returns {key: (outputs, median
    seconds, samples)}: samples[k] is round k's, so the ratio of two
    runners' samples in the same round is a paired ratio."""
    once = _run_once
    keys = list(runners)
    outs, inner = {}, {}
    for k in keys:
        outs[k] = once(runners[k])                    # warm-up (compiles)
        t0 = time.perf_counter()
        once(runners[k])                              # calibration, compiled
        t_one = time.perf_counter() - t0
        inner[k] = (max(1, math.ceil(min_sample / max(t_one, 1e-6))), t_one)
    rounds = min(repeats, 3) if any(t > 1.0 for _, t in inner.values()) else repeats
    samples = {k: [] for k in keys}
    for r in range(rounds):
        for j in range(len(keys)):
            k = keys[(j + r) % len(keys)]
            t0 = time.perf_counter()
            for _ in range(inner[k][0]):
                outs[k] = once(runners[k])
            samples[k].append((time.perf_counter() - t0) / inner[k][0])
    return {k: (runners[k].read(outs[k]), float(np.median(samples[k])), samples[k])
            for k in keys}


def paired_ratio(samples_a, samples_b):
    """The median over rounds of a's time / b's time in the same round
    (samples of :func:`timed_together`)."""
    return float(np.median(np.asarray(samples_a) / np.asarray(samples_b)))


def _angle_deg(a, b):
    """Angle between the lines of unit vectors a and b; NaN counts 90."""
    c = np.abs(np.sum(a * b, axis=1))
    return np.where(np.isnan(c), 90.0, np.degrees(np.arccos(np.clip(c, 0.0, 1.0))))


def accuracy(res: dict, normals, ref_t, ref_n, diag):
    hit, ref_hit = res["hit"], np.isfinite(ref_t)
    both = hit & ref_hit
    out = {"wrong_hit_fraction": float(np.mean(hit != ref_hit)),
           "depth_error_mean": None, "depth_error_max": None, "normal_error_deg": None}
    if both.any():
        err = np.abs(res["t"][both] - ref_t[both]) / diag
        out["depth_error_mean"] = float(err.mean())
        out["depth_error_max"] = float(err.max())
        ok = both & np.all(np.isfinite(ref_n), axis=1)
        if ok.any():
            out["normal_error_deg"] = float(_angle_deg(normals[ok], ref_n[ok]).mean())
    return out


def accuracy_subset(res: int, stride: int) -> np.ndarray:
    """Indices of the pixels (row-major) on every ``stride``-th row and column."""
    k = np.arange(0, res, stride)
    return (k[:, None] * res + k[None, :]).ravel()


def bench_surface(name, cfg: Config, log):
    spec = LIBRARY[name]()
    o, d = primary_rays(spec.bbox, cfg.res)
    rays = Rays(o, d)
    diag = float(np.linalg.norm(np.subtract(spec.bbox[1], spec.bbox[0])))
    t0 = time.perf_counter()
    degree = stability.DEGREE.get(name)
    sub = accuracy_subset(cfg.res, cfg.stride)
    ref_t = stability.nearest_root(spec, o[sub], d[sub], degree=degree, steps=cfg.scan_steps)
    ref_n = np.full((len(sub), 3), np.nan)
    hit = np.isfinite(ref_t)
    o_s, d_s = o[sub][hit].astype(np.float64), d[sub][hit].astype(np.float64)
    ref_n[hit] = stability.reference_normal(spec, o_s + ref_t[hit, None] * d_s)
    log(f"{name}: reference ({'polynomial roots' if degree else f'{cfg.scan_steps}-step scan'}) "
        f"on {len(sub)} rays in {time.perf_counter() - t0:.1f} s, {hit.mean():.1%} of them hit")
    records = []
    for make in runners(spec, rays, cfg):
        runner = make()
        res, seconds = timed(runner, cfg.repeats, cfg.min_sample)
        # Accuracy on the subset: normals only where it is hit.
        t_sub = np.full(len(o), np.inf)
        t_sub[sub] = np.where(res["hit"][sub], res["t"][sub], np.inf)
        normals = runner.normals(t_sub)[sub]
        res_sub = {"t": res["t"][sub], "hit": res["hit"][sub]}
        rec = {"surface": name, "method": runner.method, "setting": runner.setting,
               "mrays_per_s": len(o) / seconds / 1e6,
               "evals_per_ray": None if res["evals"] is None else float(res["evals"].mean()),
               "memory_bytes": runner.memory_bytes,
               **accuracy(res_sub, normals, ref_t, ref_n, diag),
               "capped_fraction": None if res["capped"] is None else float(res["capped"].mean()),
               "rays": len(o), "accuracy_rays": len(sub), "seconds": seconds,
               "build_s": runner.build_s, **runner.extra}
        records.append(rec)
        log(f"  {rec['method']:21} {rec['setting']:26} {rec['mrays_per_s']:7.2f} Mrays/s  "
            f"wrong {rec['wrong_hit_fraction']:.4f}  depth {_fmt(rec['depth_error_mean'])}")
    return records


def bench_stability(cfg: Config, log, groups=stability.GROUPS):
    """Stability records, and a note per case (its group, description and
    oracle). Cases with ``judge_t64`` judge lgshape on its float64 t64 (the
    others have only their float32 t)."""
    out, notes = [], []
    for case in stability.cases(scale=cfg.stability_scale, groups=groups):
        notes.append({"case": case.name, "group": case.group, "description": case.description,
                      "oracle": case.oracle, "rays": len(case.o),
                      "tangent": int(case.tangent.sum()), "t_min": case.t_min,
                      "judge_t64": case.judge_t64})
        rays = Rays(case.o, case.d, case.t_min)
        for make in stability_runners(case.surface, rays, cfg, case.lipschitz):
            runner = make()
            res, _ = timed(runner, 0)
            on64 = case.judge_t64 and "t64" in res
            t = np.where(res["hit"], res["t64"] if on64 else res["t"], np.inf)
            verdict = stability.judge(case, t, res["hit"], runner.normals(t))
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


# ---- Charts -----------------------------------------------------------------

FLOOR = 1e-8         # zero errors are drawn here on the log axes

METHOD_STYLE = {"lgshape": ("tab:red", "o"), "lgshape_global": ("tab:orange", "s"),
                "sphere_trace": ("tab:blue", "^"), "sphere_trace_relaxed": ("tab:cyan", "v"),
                "march": ("tab:green", "D"), "sdfgrid": ("tab:purple", "P"),
                "mesh": ("tab:brown", "X")}


def _plot_surface(axes, recs, title, legend=True):
    from matplotlib.ticker import NullFormatter
    metrics = (("wrong_hit_fraction", "pixels with a wrong hit / miss"),
               ("depth_error_mean", "mean depth error (box diagonals)"))
    for ax, (key, label) in zip(axes, metrics):
        for method, (color, marker) in METHOD_STYLE.items():
            pts = sorted((1e3 / r["mrays_per_s"], max(r[key], FLOOR))
                         for r in recs if r["method"] == method and r[key] is not None)
            if pts:
                ax.plot(*zip(*pts), color=color, marker=marker, label=method, lw=1.2, ms=5)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("time per ray (ns)")
        ax.set_ylabel(label)
        ax.axhline(FLOOR, color="0.7", lw=0.6, ls=":")
        ax.set_title(title, fontsize=9)
        ax.grid(True, which="major", alpha=0.3)
    if legend:
        axes[0].legend(fontsize=7, loc="best")


def charts(records, out_dir):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    os.makedirs(os.path.join(out_dir, "charts"), exist_ok=True)
    written = []
    surfaces = list(dict.fromkeys(r["surface"] for r in records))
    for name in surfaces:
        recs = [r for r in records if r["surface"] == name]
        fig, axes = plt.subplots(1, 2, figsize=(10, 4))
        _plot_surface(axes, recs, f"{name}: {recs[0]['rays']} rays timed, "
                      f"{recs[0]['accuracy_rays']} checked; 0 drawn at {FLOOR:g}")
        fig.tight_layout()
        path = os.path.join(out_dir, "charts", f"{name}.png")
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)
    cols = min(5, len(surfaces))
    rows = -(-len(surfaces) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.4 * cols, 3.0 * rows), squeeze=False)
    for ax, name in zip(axes.flat, surfaces):
        recs = [r for r in records if r["surface"] == name]
        _plot_surface([ax], recs, name, legend=False)
        ax.set_ylabel("")
        ax.set_xlabel("ns / ray", fontsize=8)
    for ax in list(axes.flat)[len(surfaces):]:
        ax.axis("off")
    handles, labels = axes.flat[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=8)
    fig.suptitle("Pixels with a wrong hit or miss against time per ray (log-log; 0 drawn at "
                 f"{FLOOR:g})", fontsize=10)
    fig.tight_layout(rect=(0, 0.05, 1, 0.96))
    path = os.path.join(out_dir, "charts", "all.png")
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return written + [path]


# ---- Headline figures and the report -----------------------------------------------

#: "Equal accuracy" to lgshape: at most this many more pixels wrong (as a
#: fraction) and a mean depth error of at most EQUAL_DEPTH box diagonals.
EQUAL_WRONG, EQUAL_DEPTH = 1e-3, 1e-4

#: Depth errors of lgshape above this (box diagonals) are listed in the report.
LG_DEPTH_TOLERANCE = 1e-5

#: The sphere tracer the plain speed ratio is taken against.
PLAIN_SPHERE = ("sphere_trace", "eps 1e-05 diag")


def headlines(records):
    """Per surface: lgshape's default; the plain sphere tracer; the fastest
    sphere tracer (either variant, any threshold) of equal accuracy; the most
    accurate sdfgrid and mesh at least as fast as lgshape (the fastest one
    where none is)."""
    rows = []
    for name in dict.fromkeys(r["surface"] for r in records):
        recs = [r for r in records if r["surface"] == name]
        lg = next((r for r in recs if (r["method"], r["setting"]) == ("lgshape", DEFAULT_LG)),
                  None)
        if lg is None:
            continue
        row = {"surface": name, "lgshape": lg}
        row["sphere"] = next((r for r in recs if (r["method"], r["setting"]) == PLAIN_SPHERE), None)
        st = [r for r in recs if r["method"].startswith("sphere_trace")
              and r["wrong_hit_fraction"] <= lg["wrong_hit_fraction"] + EQUAL_WRONG
              and r["depth_error_mean"] is not None and r["depth_error_mean"] <= EQUAL_DEPTH]
        row["sphere_equal"] = max(st, key=lambda r: r["mrays_per_s"]) if st else None
        for method in ("sdfgrid", "mesh"):
            cand = [r for r in recs if r["method"] == method]
            fast = [r for r in cand if r["mrays_per_s"] >= lg["mrays_per_s"]]
            pick = (min(fast, key=lambda r: (r["wrong_hit_fraction"], r["depth_error_mean"] or 0))
                    if fast else max(cand, key=lambda r: r["mrays_per_s"], default=None))
            row[method] = pick
        rows.append(row)
    return rows


def summary(rows) -> list[str]:
    """The headline sentences, from :func:`headlines`."""
    out = []
    ratios = [(h["surface"], h["sphere"]["mrays_per_s"] / h["lgshape"]["mrays_per_s"])
              for h in rows if h["sphere"]]
    if ratios:
        lo, hi = min(ratios, key=lambda x: x[1]), max(ratios, key=lambda x: x[1])
        geo = math.exp(sum(math.log(r) for _, r in ratios) / len(ratios))
        wrong = [h["sphere"]["wrong_hit_fraction"] for h in rows if h["sphere"]]
        out.append(f"- Against plain sphere tracing ({PLAIN_SPHERE[1]}), lgshape takes {geo:.2f}x "
                   f"its time per ray (geometric mean over {len(ratios)} surfaces; from "
                   f"{lo[1]:.2f}x on {lo[0]} to {hi[1]:.2f}x on {hi[0]}), while sphere "
                   f"tracing gets {_pct(min(wrong))} to {_pct(max(wrong))} of the pixels wrong "
                   f"and lgshape {_pct(max(h['lgshape']['wrong_hit_fraction'] for h in rows))} "
                   "at most.")
    eq = [h for h in rows if h["sphere_equal"]]
    names = ", ".join(f"{h['sphere_equal']['mrays_per_s'] / h['lgshape']['mrays_per_s']:.2f}x on "
                      f"{h['surface']}" for h in eq)
    out.append(f"- At equal accuracy, some sphere-tracing setting matches lgshape on {len(eq)} of "
               f"{len(rows)} surfaces" + (f"; there lgshape takes {names} its time." if eq else ".")
               + " On the others no setting gets there within 1024 steps.")
    for method in ("sdfgrid", "mesh"):
        picks = [(h["surface"], h[method]) for h in rows if h[method]]
        fast = [(n, r) for n, r in picks if r["mrays_per_s"] >= next(
            h["lgshape"]["mrays_per_s"] for h in rows if h["surface"] == n)]
        if fast:
            w = [r["wrong_hit_fraction"] for _, r in fast]
            dm = [r["depth_error_mean"] for _, r in fast if r["depth_error_mean"] is not None]
            lgd = max(h["lgshape"]["depth_error_mean"] or 0 for h in rows)
            out.append(f"- {method} at equal time (the most accurate resolution at least as fast "
                       f"as lgshape, on {len(fast)} of {len(rows)} surfaces): {_pct(min(w))} to "
                       f"{_pct(max(w))} of the pixels wrong, mean depth error {_fmt(min(dm))} to "
                       f"{_fmt(max(dm))} diagonals (lgshape: at most {_fmt(lgd)}).")
    return out


def _fmt(v, digits=2):
    if v is None:
        return "–"
    if isinstance(v, int) or (isinstance(v, float) and v.is_integer() and abs(v) < 1e6):
        return str(int(v))
    if v == 0:
        return "0"
    return f"{v:.{digits}e}" if abs(v) < 1e-2 or abs(v) >= 1e4 else f"{v:.{digits + 1}g}"


def _pct(v):
    return "–" if v is None else f"{100 * v:.2f}%"


def _evals(v):
    return "–" if v is None else (f"{v:.1f}" if v < 100 else f"{v:.0f}")


def _kib(b):
    return "–" if b is None else ("0" if b == 0 else f"{b / 1024:,.0f}")


def report(results, command, written) -> str:
    meta, records, stab = results["meta"], results["records"], results["stability"]
    L = []
    L.append("# Benchmarks: speed against accuracy\n")
    L.append(f"Generated by `{command}` on {meta['date']}; every number below comes from that "
             "run (its `results.json` holds them all, with the build times).\n")
    m = meta["machine"]
    L.append(f"- Machine: {m['cpu']}, {m['nproc']} cores (`nproc`), {m['platform']}; load "
             f"average at the start {m['loadavg']} (the cores are shared).")
    L.append(f"- Software: Python {m['python']}, Mitsuba {m['mitsuba']} (`{VARIANT}`), "
             f"Dr.Jit {m['drjit']}, lgshape at {meta['git']}.")
    L.append(f"- Rays: {meta['res']} x {meta['res']} primary rays per surface from a fixed camera "
             f"(`lgshape.camera`); a time is the median of {meta['repeats']} samples after a "
             f"warm-up (3 where one trace takes over a second), each sample repeating the trace "
             f"for at least {meta['min_sample']} s, with the rays and the acceleration structure "
             "already built; lgshape and the marching and sphere-tracing baselines run as "
             "frozen functions (`dr.freeze`: recorded once, then replayed without tracing "
             "their Python code again). Accuracy is measured on the same traces, "
             + ("on every pixel." if meta['stride'] == 1 else
                f"on the pixels whose row and column are multiples of {meta['stride']} "
                f"({meta['accuracy_rays']} rays)."))
    L.append("- Accuracy against a float64 reference: polynomial roots for the algebraic "
             f"surfaces, a {meta['scan_steps']}-step scan with bisection for the others. Depth "
             "error in box diagonals over the pixels both hit; normal error is the angle between "
             "normal lines (orientation ignored), mean over those pixels.")
    L.append("- Memory: the acceleration structure only: lgshape's brick map and, up to depth "
             "8, its walk's dense table (four bits a cell: 1 MB at depth 7), with, up to depth "
             "7, eight octant tables of the same size; sdfgrid's samples "
             "(float32); the mesh's vertex, normal and index buffers (Embree's BVH and "
             "sdfgrid's per-voxel boxes, internal to Mitsuba, not included). Sphere tracing "
             "and marching keep none.\n")
    L.append("Methods: `lgshape` (the guaranteed search with local interval bounds, modes "
             "`interval` and `taylor`, pruning depth 2^d cells per axis); `lgshape_global` "
             "(the seed's global constants: one G over the box, and with the seed's global-L "
             "pruning); `sphere_trace` / `sphere_trace_relaxed` (Hart's sphere tracing with the "
             "valid global L from interval arithmetic, plain and over-relaxed by 1.6, "
             "terminating at a distance bound eps, 1024 steps at most); `march` (fixed steps, "
             "24 bisections); `sdfgrid` (Mitsuba's native shape fed f / |grad f| sampled at the "
             "grid vertices, a first-order distance with the signs of f, which halves the "
             "depth error of raw f; it intersects the zero set of the trilinear interpolant); "
             "`mesh` (scikit-image marching cubes of the same samples, with "
             "area-weighted vertex normals, traced by Embree in Mitsuba).\n")

    L.append("## Headline\n")
    rows = headlines(records)
    L += summary(rows)
    L.append("")
    L.append(f"lgshape at its default (`{DEFAULT_LG}`) against: plain sphere tracing "
             f"(`{PLAIN_SPHERE[1]}`); the fastest sphere tracer of equal accuracy (either variant, "
             f"any threshold, at most {EQUAL_WRONG:.1%} more wrong pixels and a mean depth error "
             f"of at most {EQUAL_DEPTH:g} diagonals); the most accurate sdfgrid and mesh at least "
             "as fast as lgshape (the fastest where none is). Ratios are time per ray, lgshape's "
             "over the other's.\n")
    L.append("| surface | lgshape Mrays/s, wrong px | sphere tracing: Mrays/s, wrong px, "
             "depth err | ratio | sphere tracing at equal accuracy | ratio | sdfgrid at equal "
             "time: wrong px, depth err | mesh at equal time: wrong px, depth err |")
    L.append("|---|---|---|---|---|---|---|---|")
    for h in rows:
        lg, sp, eq = h["lgshape"], h["sphere"], h["sphere_equal"]
        plain = ("–", "–") if sp is None else (
            f"{sp['mrays_per_s']:.2f}, {_pct(sp['wrong_hit_fraction'])}, "
            f"{_fmt(sp['depth_error_mean'])}",
            f"{sp['mrays_per_s'] / lg['mrays_per_s']:.2f}")
        equal = ("none", "–") if eq is None else (
            f"{eq['method']} {eq['setting']}: {eq['mrays_per_s']:.2f} Mrays/s",
            f"{eq['mrays_per_s'] / lg['mrays_per_s']:.2f}")
        cells = []
        for method in ("sdfgrid", "mesh"):
            r = h[method]
            slower = r is not None and r["mrays_per_s"] < lg["mrays_per_s"]
            cells.append("–" if r is None else
                         ("none as fast; fastest: " if slower else "")
                         + f"{r['setting']} ({r['mrays_per_s']:.2f} Mrays/s): "
                         f"{_pct(r['wrong_hit_fraction'])}, {_fmt(r['depth_error_mean'])}")
        L.append(f"| {h['surface']} | {lg['mrays_per_s']:.2f}, {_pct(lg['wrong_hit_fraction'])} | "
                 f"{plain[0]} | {plain[1]} | {equal[0]} | {equal[1]} | {cells[0]} | {cells[1]} |")
    L.append("")
    L.append("![error against time, all surfaces](charts/all.png)\n")
    own = [r for r in records if r["method"].startswith("lgshape")
           and (r["wrong_hit_fraction"] > 0 or (r["capped_fraction"] or 0) > 0
                or (r["depth_error_max"] or 0) > LG_DEPTH_TOLERANCE)]
    L.append("### Where lgshape itself falls short\n")
    L.append(f"lgshape records with a wrong pixel, a ray at the iteration cap, or a depth error "
             f"above {LG_DEPTH_TOLERANCE:g} diagonals (its refinement tolerance is 1e-6):"
             + ("" if own else " none.") + "\n")
    for r in own:
        L.append(f"- {r['surface']}, {r['method']} `{r['setting']}`: "
                 f"{_pct(r['wrong_hit_fraction'])} wrong, {_pct(r['capped_fraction'])} capped, "
                 f"depth error max {_fmt(r['depth_error_max'])}.")
    L.append("")

    L.append("## Stability suite\n")
    L.append("Missed hits / false hits / rays at the iteration cap / NaNs per case and method "
             "(`–`: the method has no iteration cap). A ray is missed when the reference "
             f"has a root and the method reports none or one more than "
             f"{stability.TOLERANCE:g} diagonals beyond it (capped rays with a root count as "
             "missed too); a false hit is a hit with no root there. Tangent rays (either answer "
             "is right) are excluded from both counts and listed. `(refused)`: the method "
             "cannot be built for that f (the seed's global L or G is infinite) and reports "
             "no hit; `(no geometry)`: the grid samples have no sign change.\n")
    keys = list(dict.fromkeys((r["method"], r["setting"]) for r in stab))
    notes = results["cases"]
    for group in dict.fromkeys(c.get("group", stability.FEATURES) for c in notes):
        in_group = [c for c in notes if c.get("group", stability.FEATURES) == group]
        L.append(f"### {group}\n")
        if group == stability.DOMAIN:
            L.append("f scaled by 1e-30 to 1e30, fast-growing f, f undefined in part of its "
                     "box (a pole, domain edges, an undefined gap), signed-distance primitives "
                     "built with min / max / abs / sqrt, geometry far from the origin, and "
                     "degenerate rays. Where a case is marked (t64), lgshape is judged on its "
                     "float64 t (`RayResult.t64`, the search's answer before rounding to "
                     "Mitsuba's float32 t) and the other methods on their float32 t.\n")
        L.append("| case | rays (tangent) | " + " | ".join(f"{m}<br>{s}" for m, s in keys)
                 + " |")
        L.append("|---|---|" + "---|" * len(keys))
        for c in in_group:
            rows = {(r["method"], r["setting"]): r for r in stab if r["case"] == c["case"]}
            if not rows:
                continue
            first = next(iter(rows.values()))
            cells = []
            for k in keys:
                r = rows.get(k)
                note = (r or {}).get("note") or ""
                if r is None:
                    cells.append("")
                else:
                    cells.append(f"{r['missed']} / {r['false_hits']} / {_fmt(r['capped'])} / "
                                 f"{r['nans']}" + ("<br>(refused)" if note.startswith("refused")
                                                   else "<br>(no geometry)" if note else ""))
            mark = " (t64)" if c.get("judge_t64") else ""
            L.append(f"| {c['case']}{mark} | {first['rays']} ({first['tangent_excluded']}) | "
                     + " | ".join(cells) + " |")
        L.append("")
        for c in in_group:
            L.append(f"- **{c['case']}** ({c['rays']} rays, {c['tangent']} tangent): "
                     f"{c['description']}. Oracle: {c['oracle']}.")
        L.append("")

    if results.get("speed"):
        from . import benchspeed
        L += benchspeed.report(results["speed"])
    if results.get("scale"):
        from . import benchscale
        L += benchscale.report(results["scale"], meta["res"])
    if results.get("temporal"):
        from . import benchtemporal
        L += benchtemporal.report(results["temporal"])
    L.append("## All records\n")
    L.append("Depth errors in box diagonals; `–` where a figure has no meaning (no evaluations "
             "of f, no pixel hit by both).\n")
    for name in dict.fromkeys(r["surface"] for r in records):
        L.append(f"### {name}\n")
        L.append(f"![{name}](charts/{name}.png)\n")
        L.append("| method | setting | Mrays/s | evals/ray | memory KiB | wrong px | "
                 "depth err mean | depth err max | normal err ° | capped |")
        L.append("|---|---|---|---|---|---|---|---|---|---|")
        for r in (r for r in records if r["surface"] == name):
            L.append(f"| {r['method']} | {r['setting']} | {r['mrays_per_s']:.2f} | "
                     f"{_evals(r['evals_per_ray'])} | {_kib(r['memory_bytes'])} | "
                     f"{_pct(r['wrong_hit_fraction'])} | {_fmt(r['depth_error_mean'])} | "
                     f"{_fmt(r['depth_error_max'])} | {_fmt(r['normal_error_deg'])} | "
                     f"{_pct(r['capped_fraction'])} |")
        L.append("")
    return "\n".join(L) + "\n"


# ---- Command line ---------------------------------------------------------------

def _machine():
    import drjit
    import mitsuba
    cpu = "unknown"
    try:
        with open("/proc/cpuinfo") as fh:
            cpu = next((ln.split(":", 1)[1].strip() for ln in fh
                        if ln.startswith("model name")), cpu)
    except OSError:
        pass
    load = os.getloadavg() if hasattr(os, "getloadavg") else ()
    return {"nproc": os.cpu_count(), "cpu": cpu, "platform": platform.platform(),
            "python": platform.python_version(), "mitsuba": mitsuba.__version__,
            "drjit": drjit.__version__, "loadavg": " ".join(f"{v:.2f}" for v in load)}


def _git():
    here = os.path.dirname(os.path.abspath(__file__))
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=here,
                              capture_output=True, text=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "."], cwd=here,
                               capture_output=True, text=True, timeout=10).stdout.split("\n")
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    changed = [ln[3:] for ln in dirty if ln.strip()]
    if not head:
        return "unknown"
    return head + (f" (uncommitted: {', '.join(changed)})" if changed else "")


def _parser():
    p = argparse.ArgumentParser(
        prog="lgshape bench", description="lgshape against sphere tracing, marching, Mitsuba's "
        "sdfgrid and a marching-cubes mesh: speed against accuracy, and a stability suite.")
    p.add_argument("--quick", action="store_true",
                   help="a smoke run of well under a minute: fewer rays and settings")
    p.add_argument("--out", required=True, help="output folder (results.json, charts/, "
                   "BENCHMARKS.md)")
    p.add_argument("--surfaces", nargs="+", choices=sorted(LIBRARY), metavar="NAME",
                   help="only these library surfaces")
    p.add_argument("--no-stability", dest="stability", action="store_false",
                   help="skip the stability suite")
    p.add_argument("--no-speed", dest="speed", action="store_false",
                   help="skip the speed section (camera, incoherent and shadow rays against the "
                   "sphere tracer and the mesh; the Cornell render; compile latency)")
    p.add_argument("--no-scale", dest="scale", action="store_false",
                   help="skip the scale section (cost against the number of primitives)")
    p.add_argument("--no-temporal", dest="temporal", action="store_false",
                   help="skip the temporal-stability section (animation)")
    return p


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = _parser().parse_args(argv)
    cfg = QUICK if args.quick else FULL
    surfaces = tuple(args.surfaces) if args.surfaces else cfg.surfaces
    import mitsuba as mi
    mi.set_variant(VARIANT)
    command = "lgshape bench " + " ".join(argv)
    t_start = time.perf_counter()

    def log(msg):
        print(f"[{time.perf_counter() - t_start:6.1f} s] {msg}", file=sys.stderr, flush=True)

    now = datetime.datetime.now().astimezone()
    meta = {"command": command, "date": now.isoformat(timespec="seconds"),
            "machine": _machine(), "git": _git(), "quick": bool(args.quick), "res": cfg.res,
            "repeats": cfg.repeats, "min_sample": cfg.min_sample, "stride": cfg.stride,
            "accuracy_rays": len(accuracy_subset(cfg.res, cfg.stride)),
            "scan_steps": cfg.scan_steps, "variant": VARIANT,
            "depth_error_unit": "box diagonals", "normal_error_unit": "degrees, between lines",
            "stability_tolerance": stability.TOLERANCE}
    records = []
    for name in surfaces:
        records += bench_surface(name, cfg, log)
    stab, notes = bench_stability(cfg, log) if args.stability else ([], [])
    results = {"meta": meta, "records": records, "stability": stab, "cases": notes}
    os.makedirs(os.path.join(args.out, "charts"), exist_ok=True)
    if args.speed:
        from . import benchspeed
        results["speed"] = benchspeed.run(log, quick=args.quick)
        benchspeed.chart(results["speed"], os.path.join(args.out, "charts", "speed.png"))
    if args.scale:
        from . import benchscale
        results["scale"] = benchscale.run(log, quick=args.quick, res=cfg.res,
                                          repeats=cfg.repeats)
        benchscale.chart(results["scale"], os.path.join(args.out, "charts", "scale.png"))
    if args.temporal:
        from . import benchtemporal
        results["temporal"] = benchtemporal.run(log, quick=args.quick)
        benchtemporal.chart(results["temporal"], os.path.join(args.out, "charts", "temporal.png"))
    written = charts(records, args.out)
    results["meta"]["seconds"] = round(time.perf_counter() - t_start, 1)
    with open(os.path.join(args.out, "results.json"), "w") as fh:
        json.dump(_finite(results), fh, indent=1, allow_nan=False)
    with open(os.path.join(args.out, "BENCHMARKS.md"), "w") as fh:
        fh.write(report(results, command, written))
    log(f"wrote {os.path.join(args.out, 'results.json')}, BENCHMARKS.md and {len(written)} charts")
    return 0


def _finite(v):
    """JSON-ready: numpy scalars as Python numbers, inf and NaN as null."""
    if isinstance(v, dict):
        return {k: _finite(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_finite(x) for x in v]
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return float(v) if math.isfinite(v) else None
    return v


if __name__ == "__main__":
    sys.exit(main())
