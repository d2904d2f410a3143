"""Temporal stability: the benchmark's section on animation (Kalra and Barr's
"note problem in animation": a sampling method misses a thin spike between
its samples in one frame and catches it in the next, so the spike flickers).

The animation: the library ``spikes`` surface (:func:`lgshape.surfaces.spikes`,
a ball of radius 0.5 with 14 needles about 0.02 thick, thinner towards their
tips) seen by a camera orbiting it (:func:`orbit_rays`), ``FULL.frames``
frames of ``FULL.degrees_per_frame`` each, one primary ray through the centre
of each pixel. At ``FULL.res`` x ``FULL.res`` a pixel is about 0.02 wide at
the object, so the spikes are a pixel thick at their base and a tenth of one
near their tips. Every method traces the rays of all frames in one batch,
with the runners of :mod:`lgshape.bench.common` and
:mod:`lgshape.bench.baselines` (lgshape; sphere tracing with three
Lipschitz constants; fixed-step marching; Mitsuba's sdfgrid and a
marching-cubes mesh of f / |grad f| sampled on a grid, built once: the
object is rigid, the camera moves).

**Oracle.** :func:`spikes_reference`: float64 nearest roots by a windowed
scan with bisection. Away from the core ball and from the cylinders of
radius sqrt(40) width around the seven spike lines, every term of the sum is
below e^-40 and f > 0, so the first root lies in those windows (or in a thin
shell just outside the core, inside which f <= 0); each window is sampled
every ``scan_step`` (2e-4, a hundredth of a spike's width at its base, in
units of t) and the first sign change bisected to float64 precision. It is
checked in the tests against :func:`lgshape.reference.nearest_root`'s plain
dense scan. It is the same for every method.

**Metrics**, per method (a record per method and setting):

- *wrong pixel*: the method's hit / miss differs from the oracle's, or both
  hit and |t - t_ref| > ``TOLERANCE`` (1e-2) box diagonals (a
  spike missed in front of the core, which is then hit behind it);
- *thin-feature pixels* of a frame: the pixels whose oracle hit point lies
  on a spike, i.e. more than ``FEATURE_RADIUS`` (1.1) core radii from the
  centre (the core is a ball of the core radius; a spike's base flares out
  from it smoothly). Per frame: the fraction of them that the method gets
  wrong; over the animation: the fraction of frames with at least one wrong
  thin-feature pixel, and the mean and max per-frame fractions;
- the fraction of all pixels wrong, per frame;
- *flicker*: every pixel of every frame has a state: no hit, the core, or a
  spike. The oracle's state comes from its hit point (spike: farther than
  ``FEATURE_RADIUS`` core radii from the centre); a method's state is the
  oracle's where the method is right on that pixel, else it is classified
  from its own hit point. A *toggle* is a pixel whose state changes from
  frame k to k + 1. The oracle's toggles are the motion; a method's toggles
  that the oracle does not have at the same pixel and frame pair are
  flicker (change not explained by the motion). ``flicker`` is their mean
  count per frame pair (0 for the oracle by construction, and for any method
  right on every pixel); ``missed_toggles`` are the oracle's toggles that
  the method lacks (motion it does not show); ``excess_toggles`` is the
  method's toggle count minus the oracle's, per frame pair (may be < 0).

:func:`run` returns a JSON-ready dict, :func:`chart` draws it, :func:`report`
writes its markdown section. Standalone: ``python -m lgshape.bench.temporal
--out DIR [--quick]`` (also writes an image strip of four frames). Mitsuba
and matplotlib are imported where they are used.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from dataclasses import asdict, dataclass

import numpy as np

from ..camera import look_rays
from ..expr import evaluate, gradient
from ..reference import clip_to_box, numpy_f
from ..surfaces import SPIKE_AXES, Implicit, spikes
from .baselines import sampling_runners, sphere_runner
from .common import (METHOD_STYLE, TOLERANCE, VARIANT, Rays, finite, global_L, lgshape_runner,
                     pct, stderr_log, timed)

#: Spike parameters of the animation (the library defaults).
CORE, HEIGHT, WIDTH = 0.5, 1.0, 0.01

#: Hit points farther than this many core radii from the centre are on a spike.
FEATURE_RADIUS = 1.1

#: The cylinders around the spike lines where exp(-rho^2 / width^2) >= e^-K.
WINDOW_K = 40.0

#: The shell outside the core ball scanned for roots: core + SHELL.
SHELL = 1e-3


@dataclass(frozen=True)
class TemporalConfig:
    res: int                    # res x res primary rays per frame
    frames: int
    degrees_per_frame: float    # camera azimuth step
    azimuth0: float             # first frame's azimuth (degrees about z)
    elevation: float            # camera elevation (degrees)
    distance: float             # eye distance from the centre
    fov: float                  # full field of view (degrees)
    scan_step: float            # oracle: scan step inside its windows (t units)
    st_eps: float               # sphere tracing threshold, box diagonals
    st_sample_grid: int         # grid on which the "sampled" L is taken
    march_steps: tuple          # fixed steps, as divisions of the diagonal
    grid_res: tuple             # sdfgrid / marching-cubes samples per axis
    repeats: int                # timed repeats (lgshape.bench.common.timed)


FULL = TemporalConfig(res=128, frames=24, degrees_per_frame=1.5, azimuth0=15.0, elevation=20.0,
                      distance=3.6, fov=40.0, scan_step=2e-4, st_eps=1e-5, st_sample_grid=64,
                      march_steps=(256, 1024), grid_res=(64, 128, 256), repeats=3)
QUICK = TemporalConfig(res=48, frames=6, degrees_per_frame=1.5, azimuth0=15.0, elevation=20.0,
                       distance=3.6, fov=40.0, scan_step=2e-4, st_eps=1e-5, st_sample_grid=32,
                       march_steps=(64, 256), grid_res=(64,), repeats=0)


def animation_spec() -> Implicit:
    return spikes(core=CORE, height=HEIGHT, width=WIDTH)


def spike_thickness(r, core=CORE, height=HEIGHT, width=WIDTH):
    """A lone spike's diameter at distance r from the centre (where the
    other terms are negligible): 2 width sqrt(log(height / (r^2 - core^2)))."""
    return 2 * width * math.sqrt(max(math.log(height / (r * r - core * core)), 0.0))


# ---- Camera -----------------------------------------------------------------------

def orbit_rays(res: int, azimuth_deg: float, cfg: TemporalConfig = FULL):
    """Primary rays (float32 (res^2, 3) origins, unit directions; row-major
    pixels, one ray through each pixel centre) of a pinhole camera at
    ``cfg.distance`` from the origin, looking at it, at azimuth
    ``azimuth_deg`` about the z axis and elevation ``cfg.elevation``."""
    az, el = math.radians(azimuth_deg), math.radians(cfg.elevation)
    view = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    return look_rays(cfg.distance * view, -view, res, res, cfg.fov)


def animation_rays(cfg: TemporalConfig):
    """The rays of all frames, frame after frame, and each frame's azimuth."""
    az = [cfg.azimuth0 + k * cfg.degrees_per_frame for k in range(cfg.frames)]
    rays = [orbit_rays(cfg.res, a, cfg) for a in az]
    return (np.concatenate([r[0] for r in rays]), np.concatenate([r[1] for r in rays]), az)


# ---- The float64 oracle --------------------------------------------------------------

def _quadratic_window(A, B, C, limit):
    """t where A t^2 + 2 B t + C <= limit, as [lo, hi] (lo > hi: none)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        disc = B * B - A * (C - limit)
        sq = np.sqrt(np.maximum(disc, 0.0))
        lo = (-B - sq) / A
        hi = (-B + sq) / A
    flat = A <= 1e-300                              # parallel to the axis / no direction
    inside = C <= limit
    lo = np.where(flat, np.where(inside, -np.inf, np.inf), np.where(disc >= 0, lo, np.inf))
    hi = np.where(flat, np.where(inside, np.inf, -np.inf), np.where(disc >= 0, hi, -np.inf))
    return lo, hi


def spikes_reference(spec: Implicit, o, d, core=CORE, width=WIDTH, axes=SPIKE_AXES,
                     step=2e-4, bisections=64, chunk=1024):
    """Float64 nearest root t (inf where none) of ``spec`` (a library
    ``spikes`` surface with these ``core``, ``width`` and ``axes``) along
    each ray o + t d in its box: a windowed scan (see the module text) with
    bisection of the first sign change. f is evaluated from ``spec.expr``
    in float64 (:func:`lgshape.reference.numpy_f`)."""
    o, d = np.asarray(o, np.float64), np.asarray(d, np.float64)
    lo, hi = (np.asarray(v, np.float64) for v in spec.bbox)
    F = numpy_f(spec.expr)
    out = np.full(len(o), np.inf)
    for k in range(0, len(o), chunk):
        out[k:k + chunk] = _reference_chunk(F, o[k:k + chunk], d[k:k + chunk], lo, hi, core,
                                            width, axes, step, bisections)
    return out


def _reference_chunk(F, o, d, lo, hi, core, width, axes, step, bisections):
    n = len(o)
    t0, t1 = clip_to_box(o, d, lo, hi)
    # The core ball: f <= 0 inside it, so the first root is at or before its entry.
    A = np.sum(d * d, 1)
    B = np.sum(o * d, 1)
    C = np.sum(o * o, 1)
    core_lo, _ = _quadratic_window(A, B, C, core**2)
    enters = np.isfinite(core_lo) & (core_lo <= t1)
    t_end = np.where(enters, np.maximum(core_lo, t0), t1)
    shell_lo, _ = _quadratic_window(A, B, C, (core + SHELL)**2)
    wins = [(shell_lo, np.where(enters, t_end, -np.inf))]
    limit = WINDOW_K * width**2
    for a in axes:
        a = np.asarray(a, np.float64)
        a = a / np.linalg.norm(a)
        u, v = np.cross(o, a), np.cross(d, a)
        wins.append(_quadratic_window(np.sum(v * v, 1), np.sum(u * v, 1), np.sum(u * u, 1), limit))
    wlo = np.stack([np.maximum(w[0], t0) for w in wins], 1)
    whi = np.stack([np.minimum(w[1], t_end) for w in wins], 1)
    valid = (wlo <= whi) & (t0 <= t1)[:, None]
    wlo, whi = np.where(valid, wlo, np.inf), np.where(valid, whi, np.inf)
    # Sort and merge each ray's windows (boundaries of the union have f > 0).
    order = np.argsort(wlo, 1)
    wlo, whi = np.take_along_axis(wlo, order, 1), np.take_along_axis(whi, order, 1)
    for j in range(1, wlo.shape[1]):
        prev_hi = np.maximum.accumulate(whi[:, :j], 1)[:, -1]
        join = np.isfinite(wlo[:, j]) & (wlo[:, j] <= prev_hi)
        # Fold window j into the window that reaches prev_hi: extend its end.
        whi[:, j] = np.where(join, np.maximum(whi[:, j], prev_hi), whi[:, j])
        wlo[:, j] = np.where(join, prev_hi, wlo[:, j])
    live = np.isfinite(wlo) & (whi >= wlo)
    # Samples: each window from its start to its end (both included).
    with np.errstate(invalid="ignore"):
        length = np.where(live, whi - wlo, 0.0)
    count = np.where(live, np.ceil(length / step).astype(np.int64) + 1, 0)
    ray_of = np.repeat(np.repeat(np.arange(n), wlo.shape[1]), count.ravel())
    start = np.repeat(wlo.ravel(), count.ravel())
    span = np.repeat(length.ravel(), count.ravel())
    cnt = np.repeat(count.ravel(), count.ravel())
    first = np.cumsum(count.ravel()) - count.ravel()
    idx = np.arange(len(ray_of)) - np.repeat(first, count.ravel())
    t = start + span * (idx / np.maximum(cnt - 1, 1))
    with np.errstate(all="ignore"):
        f = np.broadcast_to(F(*(o[ray_of, i] + t * d[ray_of, i] for i in range(3))), t.shape)
    root = np.full(n, np.inf)
    neg = np.flatnonzero(f <= 0)
    if len(neg):
        rays, pos = np.unique(ray_of[neg], return_index=True)
        j = neg[pos]                                 # each ray's first sample with f <= 0
        a_t = np.where(idx[j] > 0, t[np.maximum(j - 1, 0)], t[j])
        b_t = t[j]
        ro, rd = o[rays], d[rays]

        def f_at(tt):
            with np.errstate(all="ignore"):
                return np.broadcast_to(F(*(ro[:, i] + tt * rd[:, i] for i in range(3))), tt.shape)
        for _ in range(bisections):
            mid = 0.5 * (a_t + b_t)
            fm = f_at(mid)
            a_t, b_t = np.where(fm > 0, mid, a_t), np.where(fm > 0, b_t, mid)
        root[rays] = b_t
    # Entering the core: f(t_end) <= 0 exactly; rounding may say otherwise.
    return np.where(np.isinf(root) & enters & (t0 <= t1), t_end, root)


# ---- Methods -----------------------------------------------------------------------

def analytic_lipschitz(spec: Implicit, height=HEIGHT, width=WIDTH, axes=SPIKE_AXES) -> float:
    """A valid Lipschitz bound of the spikes' f over its box, by hand:
    |grad f| <= 2 |p| + height * sum_k |grad exp(-rho_k^2 / width^2)|, and
    each term's gradient is at most sqrt(2) e^-1/2 / width."""
    lo, hi = (np.asarray(v, np.float64) for v in spec.bbox)
    p_max = float(np.linalg.norm(np.maximum(np.abs(lo), np.abs(hi))))
    return 2 * p_max + height * len(axes) * math.sqrt(2) * math.exp(-0.5) / width


def sampled_lipschitz(spec: Implicit, res: int) -> float:
    """max |grad f| over res^3 grid vertices spanning the box: what an
    estimate from samples gives; not a bound (the spikes, thinner than the
    spacing, fall between the vertices)."""
    lo, hi = (np.asarray(v, np.float64) for v in spec.bbox)
    ax = [np.linspace(lo[i], hi[i], res) for i in range(3)]
    Z, Y, X = np.meshgrid(ax[2], ax[1], ax[0], indexing="ij")
    g = [np.broadcast_to(v, X.shape) for v in
         evaluate(list(gradient(spec.expr)), {"x": X, "y": Y, "z": Z})]
    return float(np.sqrt(g[0]**2 + g[1]**2 + g[2]**2).max())


def runners(spec, rays, cfg: TemporalConfig):
    """Every method and setting, built lazily (each item's make() returns a
    :class:`lgshape.bench.common.Runner`)."""
    yield lambda: lgshape_runner(spec, rays, "interval", 6)
    L_iv = global_L(spec)
    L_an = analytic_lipschitz(spec)
    L_sm = sampled_lipschitz(spec, cfg.st_sample_grid)
    for L, how in ((L_iv, "interval L"), (L_an, "analytic L"),
                   (L_sm, f"L sampled on {cfg.st_sample_grid}^3")):
        def make(L=L, how=how):
            r = sphere_runner(spec, rays, cfg.st_eps, 1.0, L=L)
            r.setting = f"{how} = {L:.3g}, eps {cfg.st_eps:g} diag"
            return r
        yield make
    yield from sampling_runners(spec, rays, cfg.march_steps, cfg.grid_res)


# ---- Metrics -------------------------------------------------------------------------

MISS, CORE_HIT, SPIKE_HIT = 0, 1, 2


def states(o, d, t, hit, core=CORE):
    """Per ray: MISS, CORE_HIT or SPIKE_HIT (hit point farther than
    FEATURE_RADIUS core radii from the centre)."""
    tt = np.where(hit, t, 0.0)
    p = o.astype(np.float64) + tt[..., None] * d.astype(np.float64)
    far = np.linalg.norm(p, axis=-1) > FEATURE_RADIUS * core
    return np.where(hit, np.where(far, SPIKE_HIT, CORE_HIT), MISS).astype(np.int8)


def judge_frames(t, hit, ref_t, o, d, diag, frames):
    """Per-frame metrics of one method against the oracle (see the module
    text); arrays of shape (frames * pixels,) in frame order."""
    ref_hit = np.isfinite(ref_t)
    P = len(t) // frames
    with np.errstate(invalid="ignore"):
        far = np.abs(np.where(hit & ref_hit, t - ref_t, 0.0)) > TOLERANCE * diag
    wrong = (hit != ref_hit) | (hit & ref_hit & far)
    s_ref = states(o, d, ref_t, ref_hit)
    s_own = states(o, d, t, hit)
    s_m = np.where(wrong, s_own, s_ref)
    wrong, s_ref, s_m = (a.reshape(frames, P) for a in (wrong, s_ref, s_m))
    feature = s_ref == SPIKE_HIT
    n_feat = feature.sum(1)
    wrong_feat = (wrong & feature).sum(1)
    tog_o = s_ref[1:] != s_ref[:-1]
    tog_m = s_m[1:] != s_m[:-1]
    flick = (tog_m & ~tog_o).sum(1)
    return {
        "wrong_feature_per_frame": (wrong_feat / np.maximum(n_feat, 1)).tolist(),
        "wrong_feature_pixels_per_frame": wrong_feat.tolist(),
        "wrong_pixels_per_frame": wrong.mean(1).tolist(),
        "frames_with_wrong_feature": float(np.mean(wrong_feat > 0)),
        "wrong_feature_mean": float(np.mean(wrong_feat / np.maximum(n_feat, 1))),
        "wrong_feature_max": float(np.max(wrong_feat / np.maximum(n_feat, 1))),
        "wrong_pixel_mean": float(wrong.mean()),
        "flicker_per_pair": flick.tolist(),
        "flicker": float(flick.mean()) if len(flick) else 0.0,
        "flicker_fraction": float(flick.mean() / P) if len(flick) else 0.0,
        "missed_toggles": float((tog_o & ~tog_m).sum(1).mean()) if len(flick) else 0.0,
        "excess_toggles": float((tog_m.sum(1) - tog_o.sum(1)).mean()) if len(flick) else 0.0,
    }, {"wrong": wrong, "state": s_m, "ref_state": s_ref}


# ---- The run --------------------------------------------------------------------------

def run(log=None, quick=False, strip=None, cfg: TemporalConfig | None = None) -> dict:
    """The temporal section: every method on the animation's rays against
    the oracle. Returns a JSON-ready dict: ``meta`` (the setup, the oracle,
    per-frame thin-feature pixel and toggle counts) and ``records`` (one per
    method and setting, the oracle first). ``strip``: a PNG path for an image
    strip of four consecutive frames (:func:`strip_image`)."""
    import mitsuba as mi
    if mi.variant() is None:
        mi.set_variant(VARIANT)
    log = log or (lambda msg: None)
    cfg = cfg or (QUICK if quick else FULL)
    t_start = time.perf_counter()
    spec = animation_spec()
    diag = float(np.linalg.norm(np.subtract(spec.bbox[1], spec.bbox[0])))
    o, d, azimuths = animation_rays(cfg)
    P = cfg.res * cfg.res
    t0 = time.perf_counter()
    ref_t = spikes_reference(spec, o, d, step=cfg.scan_step)
    ref_s = time.perf_counter() - t0
    ref_hit = np.isfinite(ref_t)
    ref_state = states(o, d, ref_t, ref_hit).reshape(cfg.frames, P)
    n_feat = (ref_state == SPIKE_HIT).sum(1)
    tog = (ref_state[1:] != ref_state[:-1]).sum(1)
    log(f"temporal: {cfg.frames} frames of {cfg.res}x{cfg.res} rays; oracle (windowed float64 "
        f"scan) in {ref_s:.1f} s; thin-feature pixels per frame {n_feat.min()}-{n_feat.max()}, "
        f"oracle toggles per frame pair {tog.mean() if len(tog) else 0:.1f}")
    oracle_rec = {"method": "oracle", "setting": f"float64 windowed scan, step {cfg.scan_step:g}",
                  "mrays_per_s": None, "seconds": ref_s, "build_s": 0.0, "evals_per_ray": None,
                  "capped_fraction": None, "memory_bytes": None}
    m, _ = judge_frames(ref_t, ref_hit, ref_t, o, d, diag, cfg.frames)
    oracle_rec.update(m)
    records = [oracle_rec]
    traces = {"oracle": (ref_t, ref_hit)}
    rays = Rays(o, d)
    for make in runners(spec, rays, cfg):
        runner = make()
        res, seconds = timed(runner, cfg.repeats, 0.0)
        t = np.where(res["hit"], res["t"], np.inf)
        metrics, _ = judge_frames(t, res["hit"], ref_t, o, d, diag, cfg.frames)
        rec = {"method": runner.method, "setting": runner.setting,
               "mrays_per_s": len(o) / seconds / 1e6, "seconds": seconds,
               "build_s": runner.build_s,
               "evals_per_ray": None if res["evals"] is None else float(res["evals"].mean()),
               "capped_fraction": None if res["capped"] is None else float(res["capped"].mean()),
               "memory_bytes": runner.memory_bytes, **metrics,
               **{k: v for k, v in runner.extra.items() if k in ("lipschitz_L", "triangles",
                                                                  "note")}}
        records.append(rec)
        traces[(runner.method, runner.setting)] = (t, res["hit"])
        log(f"  {rec['method']:13} {rec['setting']:42} wrong thin-feature px "
            f"{rec['wrong_feature_mean']:.2%} (frames {rec['frames_with_wrong_feature']:.0%}), "
            f"wrong px {rec['wrong_pixel_mean']:.3%}, flicker {rec['flicker']:.1f} px/pair")
    meta = {"config": asdict(cfg), "surface": repr(spec), "core": CORE, "height": HEIGHT,
            "width": WIDTH, "diagonal": diag, "azimuths": azimuths, "pixels": P,
            "feature_radius": FEATURE_RADIUS, "tolerance": TOLERANCE,
            "pixel_size": 2 * cfg.distance * math.tan(math.radians(cfg.fov) / 2) / cfg.res,
            "spike_thickness": {f"{r:g}": spike_thickness(r) for r in (0.6, 0.8, 1.0, 1.1)},
            "oracle": ("float64 windowed scan of f (lgshape.bench.temporal.spikes_reference): "
                       f"step {cfg.scan_step:g} inside the core shell and the cylinders "
                       f"rho^2 <= {WINDOW_K:g} width^2 around the spike lines, first sign "
                       "change bisected"),
            "oracle_seconds": ref_s, "feature_pixels_per_frame": n_feat.tolist(),
            "oracle_toggles_per_pair": tog.tolist(),
            "seconds": round(time.perf_counter() - t_start, 1)}
    results = {"meta": meta, "records": records}
    if strip:
        strip_image(results, traces, o, d, strip)
        meta["strip"] = strip
    return results


# ---- Charts ---------------------------------------------------------------------------

def _label(r):
    return f"{r['method']} {r['setting']}"


def _style(r, i):
    color, marker = METHOD_STYLE.get(r["method"], ("black", "o"))
    return color, marker, ("-", "--", ":", "-.")[i % 4]


def chart(results, path):
    """Two panels: wrong thin-feature pixels per frame (one line per method
    and setting) and the flicker per method (bars). Writes ``path`` (PNG)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    recs = [r for r in results["records"] if r["method"] != "oracle"]
    frames = results["meta"]["config"]["frames"]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(13, 6.6), gridspec_kw={"width_ratios": [1.2, 1]})
    seen = {}
    for r in recs:
        i = seen[r["method"]] = seen.get(r["method"], -1) + 1
        color, marker, ls = _style(r, i)
        a1.plot(range(frames), 100 * np.asarray(r["wrong_feature_per_frame"]), color=color,
                marker=marker, ls=ls, ms=3.5, lw=1.2, label=_label(r))
    a1.set_xlabel("frame")
    a1.set_ylabel("thin-feature pixels wrong (%)")
    a1.set_title("Wrong thin-feature pixels per frame (against the float64 oracle)", fontsize=9)
    a1.set_ylim(-2, 102)
    a1.grid(True, alpha=0.3)
    a1.legend(fontsize=6.5, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=2,
              frameon=False)
    names = [_label(r) for r in recs]
    vals = [r["flicker"] for r in recs]
    seen = {}
    colors = []
    for r in recs:
        i = seen[r["method"]] = seen.get(r["method"], -1) + 1
        colors.append(_style(r, i)[0])
    y = np.arange(len(recs))
    a2.barh(y, vals, color=colors)
    a2.set_yticks(y)
    a2.set_yticklabels(names, fontsize=6.5)
    a2.invert_yaxis()
    for yi, v in zip(y, vals):
        a2.text(v, yi, f" {v:.1f}", va="center", fontsize=7)
    a2.set_xlabel("flicker: pixels per frame pair whose state changes\n"
                  "(miss / core / spike) where the oracle's does not")
    tog = results["meta"]["oracle_toggles_per_pair"]
    a2.set_title(f"Flicker (the oracle: 0; its own motion toggles {np.mean(tog):.1f} "
                 "pixels per pair)", fontsize=9)
    a2.grid(True, axis="x", alpha=0.3)
    cfg = results["meta"]["config"]
    fig.suptitle(f"Temporal stability: spikes, camera orbiting {cfg['degrees_per_frame']:g}° per "
                 f"frame, {frames} frames of {cfg['res']}x{cfg['res']} rays", fontsize=10)
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def _tile(t, hit, ref_t, ref_hit, wrong, state, res):
    """RGB tile: hits grey by depth (spike hits white), missed surface
    (oracle hit, method no hit or a hit behind) red, false hits (no oracle
    hit, or a hit in front) cyan, no hit black."""
    img = np.zeros((res * res, 3))
    tt = np.where(hit, t, np.nan)
    fin = np.isfinite(ref_t)
    near, far = (np.nanmin(ref_t[fin]), np.nanmax(ref_t[fin])) if fin.any() else (0.0, 1.0)
    shade = 0.85 - 0.6 * np.clip((tt - near) / max(far - near, 1e-9), 0, 1)
    ok = hit & ~wrong
    img[ok] = np.nan_to_num(shade[ok])[:, None] * np.array([1.0, 1.0, 1.0])
    img[ok & (state == SPIKE_HIT)] = (1.0, 0.95, 0.55)
    missed = wrong & ref_hit & (~hit | (np.where(hit, t, np.inf) > ref_t))
    img[missed] = (0.95, 0.15, 0.1)
    img[wrong & ~missed] = (0.1, 0.8, 0.95)
    return img.reshape(res, res, 3)


#: The rows of the image strip: (method, setting prefix).
STRIP_ROWS = (("oracle", ""), ("lgshape", ""), ("sphere_trace", "L sampled"),
              ("march", ""), ("mesh", ""))


def strip_image(results, traces, o, d, path, count=4):
    """``count`` consecutive frames (columns) of the oracle, lgshape, sphere
    tracing with the sampled L, the coarsest march and the finest mesh
    (rows), coloured as :func:`_tile`."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    cfg = results["meta"]["config"]
    res, frames = cfg["res"], cfg["frames"]
    P = res * res
    ref_t, ref_hit = traces["oracle"]
    diag = results["meta"]["diagonal"]
    rows = []
    for method, prefix in STRIP_ROWS:
        keys = [k for k in traces if (k == "oracle" and method == "oracle")
                or (isinstance(k, tuple) and k[0] == method and k[1].startswith(prefix))]
        if keys:
            rows.append(keys[-1] if method == "mesh" else keys[0])
    m = int(round(0.07 * res))                       # the object leaves a margin
    crop = slice(m, res - m)
    first = max(0, frames // 2 - count // 2)
    cols = list(range(first, min(frames, first + count)))
    fig, axes = plt.subplots(len(rows), len(cols), figsize=(2.1 * len(cols) + 0.4, 2.1 * len(rows)),
                             squeeze=False)
    for i, key in enumerate(rows):
        t, hit = traces[key]
        _, extra = judge_frames(t, hit, ref_t, o, d, diag, frames)
        for j, k in enumerate(cols):
            s = slice(k * P, (k + 1) * P)
            img = _tile(t[s], hit[s], ref_t[s], ref_hit[s], extra["wrong"][k], extra["state"][k],
                        res)[crop, crop]
            ax = axes[i, j]
            ax.imshow(img, interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title(f"frame {k} ({results['meta']['azimuths'][k]:.1f}°)", fontsize=8)
            if j == 0:
                label = "float64 oracle" if key == "oracle" else f"{key[0]}\n{key[1]}"
                ax.set_ylabel(label.replace(", eps", "\neps"), fontsize=6.5)
    fig.suptitle("Primary hits, consecutive frames: white = spike, grey = core (by depth), "
                 "red = surface missed, cyan = false hit", fontsize=8)
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# ---- Report ---------------------------------------------------------------------------

def summary(results) -> list[str]:
    """Headline bullets: lgshape, then per other method its setting with the
    fewest wrong thin-feature pixels."""
    recs = [r for r in results["records"] if r["method"] != "oracle"]
    frames = results["meta"]["config"]["frames"]
    out = []
    for r in (r for r in recs if r["method"] == "lgshape"):
        out.append(f"- lgshape (`{r['setting']}`): {r['wrong_feature_max']:.0%} of the "
                   f"thin-feature pixels wrong in every one of the {frames} frames "
                   if r["wrong_feature_max"] == 0 else
                   f"- lgshape (`{r['setting']}`): thin-feature pixels wrong in "
                   f"{r['frames_with_wrong_feature']:.0%} of the frames (at most "
                   f"{pct(r['wrong_feature_max'], 1)} of them) ")
        out[-1] += (f"({pct(r['wrong_pixel_mean'], 3)} of all pixels), flicker "
                    f"{r['flicker']:.1f} pixels per frame pair, {r['mrays_per_s']:.2f} Mrays/s.")
    for method in dict.fromkeys(r["method"] for r in recs if r["method"] != "lgshape"):
        best = min((r for r in recs if r["method"] == method),
                   key=lambda r: (r["wrong_feature_mean"], r["flicker"]))
        out.append(f"- {method}, best setting (`{best['setting']}`): thin-feature pixels wrong in "
                   f"{best['frames_with_wrong_feature']:.0%} of the frames, "
                   f"{pct(best['wrong_feature_mean'], 1)} of them per frame on average, flicker "
                   f"{best['flicker']:.1f} pixels per pair, {best['mrays_per_s']:.2f} Mrays/s.")
    for r in recs:
        if r["method"].startswith("sphere_trace") and r["wrong_pixel_mean"] > 0.5:
            out.append(f"- `{r['method']} {r['setting']}` (the main benchmark's setting) stops "
                       "at the box: there |f| / L is already below eps, so its image is the box "
                       "(its flicker is the box's silhouette moving).")
        elif r["method"].startswith("sphere_trace") and (r.get("capped_fraction") or 0) > 0.05:
            out.append(f"- `{r['method']} {r['setting']}`: {pct(r['capped_fraction'], 0)} of the "
                       f"rays reach the 1024-step cap (a valid L makes its steps |f| / "
                       f"{r.get('lipschitz_L') or float('nan'):.3g}), and count as misses.")
    return out


def report(results, chart_path="charts/temporal.png", strip_path=None) -> list[str]:
    """The markdown lines of the section (``chart_path`` / ``strip_path``:
    relative links to the chart and strip, where the caller wrote them; the
    default is where ``lgshape bench`` writes the chart, beside
    BENCHMARKS.md; None: no link)."""
    meta, recs = results["meta"], results["records"]
    cfg = meta["config"]
    feat = meta["feature_pixels_per_frame"]
    tog = meta["oracle_toggles_per_pair"]
    L = ["## Temporal stability\n"]
    L.append(
        f"Kalra and Barr's \"note problem in animation\": the library `spikes` surface (a ball of "
        f"radius {meta['core']:g} with 14 needles of width parameter {meta['width']:g}) seen by a "
        f"camera orbiting it about the z axis, {cfg['degrees_per_frame']:g}° per frame, "
        f"{cfg['frames']} frames of {cfg['res']} x {cfg['res']} primary rays (one per pixel "
        f"centre; a pixel is {meta['pixel_size']:.3f} wide at the object; a spike is "
        + ", ".join(f"{v:.3f} thick at r = {r}" for r, v in meta["spike_thickness"].items())
        + f", its tip at r = {math.sqrt(meta['core']**2 + meta['height']):.3f}). The object is "
        f"rigid and the camera moves, so sdfgrid and the mesh are built once. Oracle: "
        f"{meta['oracle']}, the same for every method ({meta['oracle_seconds']:.1f} s).\n")
    L.append(
        f"- *Thin-feature pixels*: where the oracle's hit point is more than "
        f"{meta['feature_radius']:g} core radii from the centre (on a spike): "
        f"{min(feat)}-{max(feat)} per frame. A pixel is *wrong* when the method's hit / miss "
        f"differs from the oracle's or its depth is off by more than {meta['tolerance']:g} box "
        f"diagonals (a spike missed in front of the core).")
    L.append(
        "- *Flicker*: each pixel's state is no hit / core / spike (the oracle's where the method "
        "is right, else classified from the method's own hit point); flicker counts, per pair of "
        "consecutive frames, the pixels whose state changes while the oracle's does not (the "
        f"oracle's own changes are the motion: {np.mean(tog) if tog else 0:.1f} pixels per pair). "
        "0 for the oracle and for a method right everywhere; a wrong shape that moves with the "
        "object counts too (its changes are not the truth's). *Missed* toggles: the oracle's "
        "changes the method does not show; *excess*: the method's changes minus the oracle's.\n")
    L += summary(results)
    L.append("")
    L.append("| method | setting | Mrays/s | frames with a wrong thin-feature px | thin-feature px "
             "wrong, mean (max) per frame | all px wrong | flicker px / pair | missed toggles | "
             "excess toggles | capped |")
    L.append("|---|---|---|---|---|---|---|---|---|---|")
    for r in recs:
        if r["method"] == "oracle":
            continue
        L.append(f"| {r['method']} | {r['setting']} | {r['mrays_per_s']:.2f} | "
                 f"{pct(r['frames_with_wrong_feature'], 0)} | {pct(r['wrong_feature_mean'], 1)} "
                 f"({pct(r['wrong_feature_max'], 1)}) | {pct(r['wrong_pixel_mean'], 3)} | "
                 f"{r['flicker']:.1f} | {r['missed_toggles']:.1f} | {r['excess_toggles']:+.1f} | "
                 f"{pct(r.get('capped_fraction'), 1)} |")
    L.append("")
    if not cfg["repeats"]:
        L.append("(Quick run: a time is one trace, compilation included.)\n")
    else:
        L.append("Times: one trace of all frames' rays after a warm-up "
                 "(`lgshape.bench.common.timed`), the rays and the acceleration structure "
                 "already built.\n")
    if chart_path:
        L.append(f"![wrong thin-feature pixels per frame, flicker]({chart_path})\n")
    if strip_path:
        L.append(f"![consecutive frames]({strip_path})\n")
    return L


# ---- Command line ---------------------------------------------------------------------

def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m lgshape.bench.temporal",
                                description="The temporal-stability section of the benchmark.")
    p.add_argument("--quick", action="store_true")
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)
    import mitsuba as mi
    mi.set_variant(VARIANT)
    log = stderr_log()
    os.makedirs(args.out, exist_ok=True)
    strip = os.path.join(args.out, "temporal_strip.png")
    results = run(log, quick=args.quick, strip=strip)
    chart(results, os.path.join(args.out, "temporal.png"))
    with open(os.path.join(args.out, "temporal.json"), "w") as fh:
        json.dump(finite(results), fh, indent=1, allow_nan=False)
    with open(os.path.join(args.out, "TEMPORAL.md"), "w") as fh:
        fh.write("\n".join(report(results, "temporal.png", "temporal_strip.png")) + "\n")
    log(f"wrote {args.out}/temporal.json, temporal.png, temporal_strip.png, TEMPORAL.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
