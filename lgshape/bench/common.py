"""What the benchmark's sections share.

- :class:`Rays` (the rays of a run, in the forms the methods take) and
  :class:`Runner` (one method at one setting, ready to trace them);
  lgshape's runner (:func:`lgshape_runner`), the parts the baselines'
  runners share (:func:`read_ray_result`, :func:`f_normals`,
  :func:`plain_surface`, :func:`global_L`, :func:`empty_runner`) and the
  Mitsuba mesh that every mesh baseline traces (:func:`mitsuba_mesh`);
- timing: :func:`timed`, :func:`timed_together` (several runners, their
  samples interleaved) and :func:`paired_ratio`;
- what a run records about itself: :func:`machine`, :func:`git_commit`;
  :func:`finite` (results made JSON-ready); :func:`stderr_log` (the
  progress log); the number formats :func:`fmt` and :func:`pct`; the
  chart styles :data:`METHOD_STYLE`.

Dr.Jit, Mitsuba and lgshape.trace are imported where they are used, here
and in the scale section: its worker processes import this module and
time their own builds (a first Surface loads lgshape.trace).
"""
from __future__ import annotations

import math
import os
import platform
import subprocess
import sys
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

import lgshape

from .. import bounds

#: The Mitsuba variant of the benchmark (Dr.Jit's LLVM backend).
VARIANT = "llvm_ad_rgb"

#: Colour and marker of each method in the charts.
METHOD_STYLE = {"lgshape": ("tab:red", "o"), "lgshape_global": ("tab:orange", "s"),
                "sphere_trace": ("tab:blue", "^"), "sphere_trace_relaxed": ("tab:cyan", "v"),
                "march": ("tab:green", "D"), "sdfgrid": ("tab:purple", "P"),
                "mesh": ("tab:brown", "X")}


# ---- Rays and methods -------------------------------------------------------------

#: Degree of the algebraic library surfaces (their f is a polynomial): the
#: reference for them is exact polynomial roots.
DEGREE = {"sphere": 2, "torus": 4, "tangle": 4, "barth_sextic": 6, "kummer": 4,
          "chmutov6": 6, "clebsch": 3}

#: Depth tolerance of the missed / false-hit verdicts, in box diagonals.
TOLERANCE = 1e-2

#: The stability suite's case groups, in the report's order.
FEATURES = "Thin features, tangents and singular points"
DOMAIN = "Domain and scale"
GROUPS = (FEATURES, DOMAIN)


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

        from ..trace import default_array3f     # on use: see the module's note
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


def read_ray_result(out):
    """A traced (t, hit, evals, capped[, t64]) as numpy fields."""
    t, hit, evals, capped = (np.asarray(v) for v in out[:4])
    res = {"t": t.astype(np.float64), "hit": hit.astype(bool),
           "evals": evals.astype(np.float64), "capped": capped.astype(bool)}
    if len(out) > 4:                    # lgshape's float64 t (RayResult.t64)
        res["t64"] = np.asarray(out[4]).astype(np.float64)
    return res


def f_normals(surf, rays):
    """Normals at hit rays' points (NaN where t is not finite): ``surf``'s
    normal of f."""
    def normals(t):
        out = np.full((len(t), 3), np.nan)
        idx = np.flatnonzero(np.isfinite(t))
        if len(idx):
            out[idx] = np.asarray(surf.normal(rays.points(t, idx).astype(np.float32))).T
        return out
    return normals


def global_L(spec) -> float:
    """The valid global Lipschitz bound of f over the box (interval arithmetic)."""
    lo, hi = (np.asarray(v, np.float64)[None] for v in spec.bbox)
    return float(bounds.lipschitz(spec.expr, lo, hi)[0])


def lgshape_runner(spec, rays, mode, depth, t64=False):
    """``mode``: a search mode, or ``"seed"`` (global L pruning and global G).
    ``t64``: also return the float64 t (for cases judged on it)."""
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
    return Runner(method, setting, run, read_ray_result, f_normals(surf, rays),
                  int(surf.memory_bytes), build)


def plain_surface(spec):
    """A Surface as the baselines' view of f, its box and its rays (they use
    no pruning grid; the coarsest one keeps the build negligible)."""
    return lgshape.Surface(spec, depth=2)


def empty_runner(method, setting, rays, build, note, has_cap=False):
    """A method left with no geometry (e.g. no sign change on its grid), or
    refused; ``has_cap``: the method has an iteration cap (no ray reached it)."""
    n = len(rays.o)

    def read(out):
        return {"t": np.full(n, np.inf), "hit": np.zeros(n, bool), "evals": None,
                "capped": np.zeros(n, bool) if has_cap else None}
    return Runner(method, setting, lambda: (), read, lambda t: np.full((n, 3), np.nan), 0, build,
                  {"note": note})


def mitsuba_mesh(v, faces, name="marching_cubes"):
    """A Mitsuba mesh of vertices ``v`` (float (V, 3)) and ``faces`` (int
    (F, 3)) with smooth vertex normals (recomputed: area-weighted face
    normals)."""
    import mitsuba as mi
    mesh = mi.Mesh(name, len(v), len(faces), has_vertex_normals=True)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(v.astype(np.float32).ravel())
    params["faces"] = mi.UInt32(faces.astype(np.uint32).ravel())
    params.update()
    mesh.recompute_vertex_normals()
    return mesh


# ---- Measuring --------------------------------------------------------------------

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


# ---- What a run records -------------------------------------------------------------

def machine() -> dict:
    """The machine and software a run is measured on (and its load average)."""
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


def git_commit() -> str:
    """lgshape's commit, with the files of the package that differ from it."""
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))     # lgshape/
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


def finite(v):
    """JSON-ready: numpy scalars as Python numbers, inf and NaN as null."""
    if isinstance(v, dict):
        return {k: finite(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [finite(x) for x in v]
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return float(v) if math.isfinite(v) else None
    return v


def stderr_log(t_start: float | None = None):
    """A progress log: ``log(msg)`` prints msg to stderr behind the seconds
    since ``t_start`` (time.perf_counter(); default: now)."""
    t_start = time.perf_counter() if t_start is None else t_start

    def log(msg):
        print(f"[{time.perf_counter() - t_start:6.1f} s] {msg}", file=sys.stderr, flush=True)
    return log


def fmt(v, digits=2):
    """A figure for a table: '–' for None, integers as such, else 3 significant
    digits (``digits`` + 1; exponent notation below 1e-2 and from 1e4)."""
    if v is None:
        return "–"
    if isinstance(v, int) or (isinstance(v, float) and v.is_integer() and abs(v) < 1e6):
        return str(int(v))
    if v == 0:
        return "0"
    return f"{v:.{digits}e}" if abs(v) < 1e-2 or abs(v) >= 1e4 else f"{v:.{digits + 1}g}"


def pct(v, digits=2):
    """A fraction as a percentage, '–' for None."""
    return "–" if v is None else f"{100 * v:.{digits}f}%"
