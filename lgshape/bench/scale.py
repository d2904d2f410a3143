"""The benchmark's scale section: cost against the number of primitives.

Two models, N = 10 .. 10000 primitives in [-1, 1]^3 (fixed seeds):

- ``union``: min of N spheres (|p - c_i| - r_i, r_i ~ 0.6 N^(-1/3)), oracle
  analytic: the nearest ray-sphere entry (the camera is outside every
  sphere);
- ``blend``: threshold 0.5 minus the sum of N compactly supported soft blobs
  (Wyvill kernels (1 - d^2 / R_i^2)^3, R_i ~ 1.3 N^(-1/3)); oracle: the
  unpruned f along the reported hit (its sign change), in float64.

Each (model, N, form) runs in a fresh process (so its peak RSS is its own):
the build (table form and pruning grid), the first frame with a cold Dr.Jit
kernel cache (a new, empty cache folder: LLVM compile included), then the
steady trace (median of timed samples after a warm-up) of the same camera
rays. ``form``: ``tables`` (per-cell rows, lgshape's default) or
``unpruned`` (the whole expression in one fused kernel, ``tables=False``;
only up to :data:`UNPRUNED_MAX` primitives, beyond which it runs for minutes
and gigabytes). References, traced by Mitsuba's Embree on the same rays
(``scene.ray_intersect_preliminary``): ``mesh``, the marching-cubes mesh of f
sampled at :data:`MESH_RES`^3 (both models), and ``spheres``, the union as N
native Mitsuba spheres. They show how the cost of the scene itself grows
with N (more of the rays hit, through more clutter), for the ratio targets.

Standalone, a worker: ``python -m lgshape.bench.scale MODEL N FORM RES
REPEATS`` prints one record as a JSON line. A worker times its own build, so
Dr.Jit, Mitsuba, scikit-image and matplotlib, and lgshape's primitives and
trace (which a first Surface loads), are imported where they are used.
"""
from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np

import lgshape

from .. import tables as T
from ..camera import primary_rays
from .common import VARIANT, mitsuba_mesh

NS = (10, 100, 1000, 10000)
UNPRUNED_MAX = 100
MESH_RES = 256
QUICK_NS = (10, 100)
TIMEOUT = 900

#: The targets at N = 1000 (and 10000), against N = 10.
TARGETS = {"build_s": 2.0, "first_s": 5.0, "steady_ratio": 3.0, "rss_gb": 1.5,
           "steady_ratio_10000": 10.0}


def model(kind: str, n: int):
    """The model ``kind`` ("union" or "blend") of ``n`` primitives: (its
    table form, (centres, radii))."""
    from .. import primitives as P      # inside the worker's timed build
    rng = np.random.default_rng(1000 + n)
    c = rng.uniform(-1, 1, (n, 3))
    r = (0.6 if kind == "union" else 1.3) * n ** (-1 / 3) * rng.uniform(0.5 if kind == "union"
                                                                        else 0.7, 1.0, n)
    # the primitives store float32 parameters: the oracle takes the same
    c, r = (a.astype(np.float32).astype(np.float64) for a in (c, r))
    if kind == "union":
        return P.union(P.spheres(c, r)), (c, r)
    return P.blend(P.spheres(c, r), threshold=0.5), (c, r)


def union_first_root(o, d, c, r, chunk=64, ray_chunk=8192):
    """Nearest ray-sphere entry t >= 0 (float64, inf where none)."""
    if len(o) > ray_chunk:
        return np.concatenate([union_first_root(o[s:s + ray_chunk], d[s:s + ray_chunk], c, r,
                                                chunk, ray_chunk)
                               for s in range(0, len(o), ray_chunk)])
    o, d = o.astype(np.float64), d.astype(np.float64)
    A = (d * d).sum(1)[:, None]                 # float32 directions: not exactly unit
    best = np.full(len(o), np.inf)
    for s in range(0, len(c), chunk):
        oc = o[:, None, :] - c[None, s:s + chunk]
        b = (oc * d[:, None, :]).sum(-1)
        # from the point of closest approach (no cancellation)
        tc = -b / A
        P = oc + tc[..., None] * d[:, None, :]
        h2 = (r[None, s:s + chunk] ** 2 - (P * P).sum(-1)) / A
        with np.errstate(invalid="ignore"):
            t = tc - np.sqrt(h2)
        t = np.where((h2 >= 0) & (t >= 0), t, np.inf)
        best = np.minimum(best, t.min(1))
    return best


def peak_rss_gb() -> float:
    """This process's peak resident memory (VmHWM: its own address space;
    getrusage's ru_maxrss would also count the parent's peak, which Linux
    keeps across fork and exec)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 2**20
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def _timed(trace, repeats):
    """(first call s, steady samples s after a warm-up, the last result)."""
    t1 = time.perf_counter()
    out = trace()
    first = time.perf_counter() - t1
    trace()
    samples = []
    for _ in range(repeats):
        t1 = time.perf_counter()
        out = trace()
        samples.append(time.perf_counter() - t1)
    return first, samples, out


def worker(kind: str, n: int, form: str, res: int, repeats: int) -> dict:
    """One measurement (run in its own process)."""
    import drjit as dr
    from drjit.llvm.ad import Array3f
    t0 = time.perf_counter()
    tf, (c, r) = model(kind, n)
    surf = lgshape.Surface(tf, tables=(form != "unpruned"))
    if form in ("mesh", "spheres"):
        return _reference(kind, n, form, surf, c, r, res, repeats, t0)
    build = time.perf_counter() - t0
    o, d = primary_rays(surf.bbox, res)
    O, D = Array3f(o.T.copy()), Array3f(d.T.copy())
    dr.eval(O, D)

    def trace():
        out = surf.trace(O, D)
        dr.eval(out.t, out.t64, out.hit, out.capped, out.iterations)
        dr.sync_thread()
        return out
    first, samples, out = _timed(trace, repeats)
    t64, hit = np.asarray(out.t64), np.asarray(out.hit)
    rss = peak_rss_gb()                                 # before the oracle
    rec = {"model": kind, "n": n, "form": form, "build_s": build,
           "first_s": first, "first_frame_s": build + first,
           "steady_s": float(np.median(samples)), "rays": len(o),
           "hits": int(hit.sum()), "capped": int(np.asarray(out.capped).sum()),
           "iterations_mean": float(np.asarray(out.iterations).mean()),
           "rss_gb": rss,
           "cells": int(len(surf.grid.cells))}
    if surf.cell_rows is not None:
        pairs = sum(len(p) for p in surf.cell_rows.pair_row)
        rec["rows_per_cell"] = pairs / max(len(surf.cell_rows.row_cells), 1)
    tol = 1e-6 * surf.diagonal
    if kind == "union":
        ref = union_first_root(o, d, c, r)
        wrong = ~((np.isinf(ref) & ~hit) | (hit & (np.abs(t64 - ref) <= tol)))
        rec["wrong"] = int(wrong.sum())
        rec["oracle"] = "analytic nearest ray-sphere entry, every ray"
    else:
        # every hit is a sign change of the whole f within 2 tolerances
        k = np.flatnonzero(hit)
        p_m = o[k] + (t64[k] - 2 * tol)[:, None] * d[k]
        p_p = o[k] + (t64[k] + 2 * tol)[:, None] * d[k]
        fm, fp = T.evaluate_points(tf, p_m), T.evaluate_points(tf, p_p)
        rec["wrong"] = int(np.sum(np.sign(fm) * np.sign(fp) > 0))
        rec["oracle"] = "sign change of the whole f (float64) at every hit (misses not checked)"
    return rec


def _reference(kind, n, form, surf, c, r, res, repeats, t0) -> dict:
    """A reference traced by Mitsuba's Embree (see the module notes)."""
    import drjit as dr
    import mitsuba as mi
    from drjit.llvm.ad import Array3f
    mi.set_variant(VARIANT)
    if form == "spheres":
        scene = mi.load_dict({"type": "scene", **{
            f"s{i}": {"type": "sphere", "center": [float(v) for v in c[i]],
                      "radius": float(r[i])} for i in range(n)}})
    else:
        from skimage.measure import marching_cubes
        lo, hi = (np.asarray(v, np.float64) for v in surf.bbox)
        ax = [np.linspace(lo[i], hi[i], MESH_RES) for i in range(3)]
        vals = np.empty(MESH_RES ** 3)
        z, y, x = (a.ravel() for a in np.meshgrid(ax[2], ax[1], ax[0], indexing="ij"))
        step = 1 << 21
        for s in range(0, len(x), step):
            p = Array3f(x[s:s + step], y[s:s + step], z[s:s + step])
            vals[s:s + step] = np.asarray(surf.value(p))
        v, faces, _, _ = marching_cubes(vals.reshape((MESH_RES,) * 3), 0.0,
                                        spacing=tuple((hi - lo)[::-1] / (MESH_RES - 1)))
        scene = mi.load_dict({"type": "scene", "m": mitsuba_mesh(v[:, ::-1] + lo, faces)})
    build = time.perf_counter() - t0
    o, d = primary_rays(surf.bbox, res)
    ray = mi.Ray3f(mi.Point3f(o.T.copy()), mi.Vector3f(d.T.copy()))

    def trace():
        pi = scene.ray_intersect_preliminary(ray)
        dr.eval(pi.t)
        dr.sync_thread()
        return pi
    first, samples, pi = _timed(trace, repeats)
    t = np.asarray(pi.t, np.float64)
    hit = np.isfinite(t)
    rec = {"model": kind, "n": n, "form": form, "build_s": build, "first_s": first,
           "first_frame_s": build + first, "steady_s": float(np.median(samples)),
           "rays": len(o), "hits": int(hit.sum()), "capped": 0, "iterations_mean": None,
           "rss_gb": peak_rss_gb(), "reference": True}
    if kind == "union":     # hit or miss as the analytic entry says (t not compared)
        ref = union_first_root(o, d, c, r)
        rec["wrong"] = int(np.sum(np.isfinite(ref) != hit))
        rec["oracle"] = "analytic nearest ray-sphere entry: hit or miss only"
    else:
        rec["wrong"] = None
    return rec


def run(log, quick=False, res=512, repeats=5) -> list:
    """Every (model, N, form) in its own process; returns the records."""
    ns = QUICK_NS if quick else NS
    records = []
    for kind in ("union", "blend"):
        for n in ns:
            for form in ("tables", "unpruned", "spheres", "mesh"):
                if form == "unpruned" and n > (10 if quick else UNPRUNED_MAX):
                    continue
                if (form == "spheres" and kind != "union") or (form in ("spheres", "mesh")
                                                               and (quick or n == 100)):
                    continue
                with tempfile.TemporaryDirectory(prefix="lgshape-scale-") as home:
                    env = dict(os.environ, HOME=home)       # a cold Dr.Jit kernel cache
                    cmd = [sys.executable, "-m", "lgshape.bench.scale", kind, str(n), form,
                           str(res), str(repeats)]
                    try:
                        p = subprocess.run(cmd, env=env, capture_output=True, text=True,
                                           timeout=TIMEOUT)
                    except subprocess.TimeoutExpired:
                        records.append({"model": kind, "n": n, "form": form,
                                        "error": f"over {TIMEOUT} s"})
                        log(f"scale {kind} N={n} {form}: over {TIMEOUT} s")
                        continue
                if p.returncode != 0:
                    err = (p.stderr.strip().splitlines() or ["?"])[-1]
                    records.append({"model": kind, "n": n, "form": form, "error": err})
                    log(f"scale {kind} N={n} {form}: failed: {err}")
                    continue
                rec = json.loads(p.stdout.strip().splitlines()[-1])
                records.append(rec)
                log(f"scale {kind} N={n} {form}: build {rec['build_s']:.2f} s, first frame "
                    f"{rec['first_frame_s']:.2f} s, steady {rec['steady_s'] * 1e3:.1f} ms, "
                    f"RSS {rec['rss_gb']:.2f} GB, hits {rec['hits']}, wrong {rec['wrong']}")
    return records


def verdicts(records) -> list:
    """The targets, checked per model: (model, what, value, target, met)."""
    out = []
    by = {(r["model"], r["n"], r["form"]): r for r in records if "error" not in r}
    for kind in ("union", "blend"):
        base = by.get((kind, 10, "tables"))
        k = by.get((kind, 1000, "tables"))
        if base and k:
            out += [(kind, "build at N=1000 (s)", k["build_s"], TARGETS["build_s"],
                     k["build_s"] <= TARGETS["build_s"]),
                    (kind, "first frame at N=1000, cold cache (s)", k["first_frame_s"],
                     TARGETS["first_s"], k["first_frame_s"] <= TARGETS["first_s"]),
                    (kind, "steady trace N=1000 / N=10", k["steady_s"] / base["steady_s"],
                     TARGETS["steady_ratio"], k["steady_s"] / base["steady_s"] <= TARGETS["steady_ratio"]),
                    (kind, "peak RSS at N=1000 (GB)", k["rss_gb"], TARGETS["rss_gb"],
                     k["rss_gb"] <= TARGETS["rss_gb"])]
        k = by.get((kind, 10000, "tables"))
        if base and k:
            ratio = k["steady_s"] / base["steady_s"]
            out.append((kind, "steady trace N=10000 / N=10", ratio, TARGETS["steady_ratio_10000"],
                        ratio <= TARGETS["steady_ratio_10000"]))
    return out


def chart(records, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    what = [("steady_s", "steady trace (s)"), ("first_frame_s", "first frame, cold cache (s)"),
            ("rss_gb", "peak RSS (GB)")]
    for ax, (key, label) in zip(axes, what):
        if key != "steady_s":
            ax.set_prop_cycle(None)
        for kind, colour in (("union", "C0"), ("blend", "C1")):
            for form, style in (("tables", "-o"), ("unpruned", "--x"), ("mesh", ":s"),
                                ("spheres", ":^")):
                rs = sorted((r for r in records if r.get("model") == kind and r.get("form") == form
                             and "error" not in r), key=lambda r: r["n"])
                if rs and (key == "steady_s" or form in ("tables", "unpruned")):
                    ax.plot([r["n"] for r in rs], [r[key] for r in rs], style, color=colour,
                            label=f"{kind}, {form}")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("primitives N")
        ax.set_title(label)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _num(v, fmt=".1f") -> str:
    return "–" if v is None else format(v, fmt)


def _rows(r) -> str:
    return "–" if r.get("rows_per_cell") is None else f"{r['rows_per_cell']:.1f}"


def report(records, res) -> list:
    L = ["## Scale: cost against the number of primitives\n",
         f"Union of N random spheres and blend of N soft blobs, {res} x {res} camera rays; each "
         "row in a fresh process (build, then the first frame with an empty Dr.Jit kernel "
         "cache: compile included; steady = median after warm-up). `tables`: per-cell rows "
         "(lgshape's default; rows/cell: rows per row cell of 2 x 2 x 2 cells); `unpruned`: "
         "the whole expression in one fused kernel. References traced by Mitsuba's Embree "
         f"on the same rays: `mesh`, the marching-cubes mesh of f at {MESH_RES}^3 samples; "
         "`spheres`, the union as N native Mitsuba spheres. Oracles: "
         "the union's analytic nearest ray-sphere entry on every ray (for the references, hit "
         "or miss only); for the blend, a sign change of the whole f (float64) at every hit "
         "(its misses are not checked).\n",
         "![scale](charts/scale.png)\n",
         "| model | N | form | build s | first frame s | steady ms | peak RSS GB | rows/cell | "
         "iterations/ray | hits | wrong | capped |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in records:
        if "error" in r:
            L.append(f"| {r['model']} | {r['n']} | {r['form']} | {r['error']} |||||||||")
            continue
        L.append(f"| {r['model']} | {r['n']} | {r['form']} | {r['build_s']:.2f} | "
                 f"{r['first_frame_s']:.2f} | {r['steady_s'] * 1e3:.1f} | {r['rss_gb']:.2f} | "
                 f"{_rows(r)} | {_num(r['iterations_mean'])} | "
                 f"{r['hits']} | {_num(r['wrong'], '')} | {r['capped']} |")
    by = {(r["model"], r["n"], r["form"]): r for r in records if "error" not in r}
    L += ["", "Against N = 10 of the same form: the steady trace of lgshape (`tables`) and of "
          "the references, which show how the scene's own cost grows with N, and the rays "
          "that hit (lgshape's):\n", "| model | ratio | N = 100 | N = 1000 | N = 10000 |",
          "|---|---|---|---|---|"]
    for kind in ("union", "blend"):
        for form, key in (("tables", "steady_s"), ("mesh", "steady_s"), ("spheres", "steady_s"),
                          ("tables", "hits")):
            base = by.get((kind, 10, form))
            if base:
                cells = [f"{by[(kind, n, form)][key] / base[key]:.2f}x"
                         if (kind, n, form) in by else "–" for n in (100, 1000, 10000)]
                what = "rays that hit" if key == "hits" else f"steady trace, {form}"
                L.append(f"| {kind} | {what} | " + " | ".join(cells) + " |")
    v = verdicts(records)
    if v:
        L += ["", "Targets (issue 9):\n", "| model | measure | value | target | met |",
              "|---|---|---|---|---|"]
        L += [f"| {k} | {w} | {val:.2f} | <= {t:g} | {'yes' if ok else '**no**'} |"
              for k, w, val, t, ok in v]
    return L + [""]


if __name__ == "__main__":
    kind, n, form, res, repeats = sys.argv[1], int(sys.argv[2]), sys.argv[3], int(sys.argv[4]), \
        int(sys.argv[5])
    print(json.dumps(worker(kind, n, form, res, repeats)))
