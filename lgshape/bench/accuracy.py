"""The benchmark's accuracy section: speed against accuracy on primary
rays, and the stability suite.

For each library surface, the same primary rays (:mod:`lgshape.camera`, one
fixed camera per surface) go through every method and setting of
:func:`runners` on the same backend (Dr.Jit LLVM, Mitsuba's ``llvm_ad_rgb``):

- ``lgshape``: the guaranteed search with local bounds (search modes
  ``interval`` and ``taylor``, pruning depths); ``lgshape_global``: the
  seed's global constants (one G for the box, with and without the global-L
  pruning);
- ``sphere_trace`` and ``sphere_trace_relaxed`` (over-relaxation 1.6) with
  the valid global Lipschitz bound L of interval arithmetic, at several
  termination thresholds; ``march``: fixed steps with bisection;
- ``sdfgrid``: Mitsuba's native shape, fed f / |grad f| sampled on a grid
  over the box (:func:`lgshape.bench.baselines.sample_grid`; it intersects
  the zero set of the trilinear interpolant of the samples, voxel by voxel);
- ``mesh``: scikit-image's marching cubes of the same samples as a Mitsuba
  mesh (smooth vertex normals from its faces), traced by Embree.

Metrics per record (:func:`bench_surface`): Mrays/s (the median of timed
samples after a warm-up, rays and acceleration structure already built, see
:func:`lgshape.bench.common.timed`), function evaluations per ray (where the
method evaluates f), the memory of the acceleration structure, and, on the
same traces (every pixel, or a regular subset of them), accuracy against a
float64 reference (:func:`lgshape.reference.nearest_root`: polynomial roots
for algebraic surfaces, a dense scan otherwise): the fraction of pixels with
a wrong hit or miss, the depth error |t - t_ref| in box diagonals over the
pixels both hit (mean and max), and the mean angle between the method's
normal line and the float64 gradient at the reference hit (degrees; a NaN
normal counts 90). Then the stability suite (:mod:`lgshape.bench.stability`) on
the same methods, one setting each (:func:`stability_runners`; run by
:func:`lgshape.bench.stability.run`).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..camera import primary_rays
from ..surfaces import LIBRARY
from ..trace import DEFAULT_DEPTH
from .baselines import Samples, march_runner, mesh_runner, sampling_runners, sdfgrid_runner, \
    sphere_runner
from ..reference import nearest_root, reference_normal
from .common import DEGREE, Rays, empty_runner, fmt, lgshape_runner, timed


@dataclass(frozen=True)
class Config:
    """The settings of a run of this section and the stability suite."""
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


# ---- Methods ----------------------------------------------------------------------

def runners(spec, rays, cfg: Config):
    """Every method and setting of the primary-ray benchmark, built lazily."""
    for depth in cfg.depths:
        yield lambda depth=depth: lgshape_runner(spec, rays, "interval", depth)
    for mode in cfg.modes:
        yield lambda mode=mode: lgshape_runner(spec, rays, mode, DEFAULT_DEPTH)
    for relax in (1.0, 1.6):
        for eps in cfg.st_eps:
            yield lambda eps=eps, relax=relax: sphere_runner(spec, rays, eps, relax)
    yield from sampling_runners(spec, rays, cfg.march_steps, cfg.grid_res)


def _seed_runner(spec, rays):
    """The seed's setting, or, where f has no finite global L over its box
    (a pole, a sqrt at the edge of its domain), a record of its refusal: no
    hits, no ray capped, and the reason in ``note``."""
    try:
        return lgshape_runner(spec, rays, "seed", DEFAULT_DEPTH, t64=True)
    except ValueError as err:
        return empty_runner("lgshape_global", f"global L and G, depth {DEFAULT_DEPTH}", rays, 0.0,
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


# ---- Measuring --------------------------------------------------------------------

def _angle_deg(a, b):
    """Angle between the lines of unit vectors a and b; NaN counts 90."""
    c = np.abs(np.sum(a * b, axis=1))
    return np.where(np.isnan(c), 90.0, np.degrees(np.arccos(np.clip(c, 0.0, 1.0))))


def accuracy(res: dict, normals, ref_t, ref_n, diag):
    """The accuracy metrics of one trace (``res``: t, hit) against the
    reference's t and normals, depth errors in units of ``diag``."""
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
    """The records of one library surface: every method of :func:`runners`
    timed on its primary rays and judged against the float64 reference."""
    spec = LIBRARY[name]()
    o, d = primary_rays(spec.bbox, cfg.res)
    rays = Rays(o, d)
    diag = float(np.linalg.norm(np.subtract(spec.bbox[1], spec.bbox[0])))
    t0 = time.perf_counter()
    degree = DEGREE.get(name)
    sub = accuracy_subset(cfg.res, cfg.stride)
    ref_t = nearest_root(spec, o[sub], d[sub], degree=degree, steps=cfg.scan_steps)
    ref_n = np.full((len(sub), 3), np.nan)
    hit = np.isfinite(ref_t)
    o_s, d_s = o[sub][hit].astype(np.float64), d[sub][hit].astype(np.float64)
    ref_n[hit] = reference_normal(spec, o_s + ref_t[hit, None] * d_s)
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
            f"wrong {rec['wrong_hit_fraction']:.4f}  depth {fmt(rec['depth_error_mean'])}")
    return records
