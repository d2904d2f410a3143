"""The benchmark's report, BENCHMARKS.md (:func:`report`), and the charts of
the accuracy section (:func:`charts`: error against time per ray, one curve
per method, per surface and for all surfaces).

The report: the run's set-up, the headline comparison (:func:`headlines`,
:func:`summary`), the stability suite's tables, the sections of speed, scale
and temporal stability (each written by its own module's ``report``), and
every record. matplotlib (the ``bench`` extra) is imported where it draws.
"""
from __future__ import annotations

import math
import os

from .common import DOMAIN, FEATURES, METHOD_STYLE, TOLERANCE, VARIANT, fmt, pct


# ---- Charts -----------------------------------------------------------------

FLOOR = 1e-8         # zero errors are drawn here on the log axes


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
    """DIR/charts/<surface>.png per surface and DIR/charts/all.png; their paths."""
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


def headlines(records, default_lg):
    """Per surface: lgshape's default; the plain sphere tracer; the fastest
    sphere tracer (either variant, any threshold) of equal accuracy; the most
    accurate sdfgrid and mesh at least as fast as lgshape (the fastest one
    where none is)."""
    rows = []
    for name in dict.fromkeys(r["surface"] for r in records):
        recs = [r for r in records if r["surface"] == name]
        lg = next((r for r in recs if (r["method"], r["setting"]) == ("lgshape", default_lg)),
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
                   f"tracing gets {pct(min(wrong))} to {pct(max(wrong))} of the pixels wrong "
                   f"and lgshape {pct(max(h['lgshape']['wrong_hit_fraction'] for h in rows))} "
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
                       f"as lgshape, on {len(fast)} of {len(rows)} surfaces): {pct(min(w))} to "
                       f"{pct(max(w))} of the pixels wrong, mean depth error {fmt(min(dm))} to "
                       f"{fmt(max(dm))} diagonals (lgshape: at most {fmt(lgd)}).")
    return out


def _evals(v):
    return "–" if v is None else (f"{v:.1f}" if v < 100 else f"{v:.0f}")


def _kib(b):
    return "–" if b is None else ("0" if b == 0 else f"{b / 1024:,.0f}")


def report(results, command, written, sections=(), default_lg="interval, depth 7") -> str:
    """BENCHMARKS.md of a run's results (``command``: the command line that
    made them; ``written``: the charts' paths; ``sections``: the speed,
    scale and temporal sections' own pages, lists of lines, from the driver,
    which alone imports the sections; ``default_lg``: lgshape's default
    setting, as the accuracy section names it)."""
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
    rows = headlines(records, default_lg)
    L += summary(rows)
    L.append("")
    L.append(f"lgshape at its default (`{default_lg}`) against: plain sphere tracing "
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
            f"{sp['mrays_per_s']:.2f}, {pct(sp['wrong_hit_fraction'])}, "
            f"{fmt(sp['depth_error_mean'])}",
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
                         f"{pct(r['wrong_hit_fraction'])}, {fmt(r['depth_error_mean'])}")
        L.append(f"| {h['surface']} | {lg['mrays_per_s']:.2f}, {pct(lg['wrong_hit_fraction'])} | "
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
                 f"{pct(r['wrong_hit_fraction'])} wrong, {pct(r['capped_fraction'])} capped, "
                 f"depth error max {fmt(r['depth_error_max'])}.")
    L.append("")

    L.append("## Stability suite\n")
    L.append("Missed hits / false hits / rays at the iteration cap / NaNs per case and method "
             "(`–`: the method has no iteration cap). A ray is missed when the reference "
             f"has a root and the method reports none or one more than "
             f"{TOLERANCE:g} diagonals beyond it (capped rays with a root count as "
             "missed too); a false hit is a hit with no root there. Tangent rays (either answer "
             "is right) are excluded from both counts and listed. `(refused)`: the method "
             "cannot be built for that f (the seed's global L or G is infinite) and reports "
             "no hit; `(no geometry)`: the grid samples have no sign change.\n")
    keys = list(dict.fromkeys((r["method"], r["setting"]) for r in stab))
    notes = results["cases"]
    for group in dict.fromkeys(c.get("group", FEATURES) for c in notes):
        in_group = [c for c in notes if c.get("group", FEATURES) == group]
        L.append(f"### {group}\n")
        if group == DOMAIN:
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
                    cells.append(f"{r['missed']} / {r['false_hits']} / {fmt(r['capped'])} / "
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

    for lines in sections:
        L += lines
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
                     f"{pct(r['wrong_hit_fraction'])} | {fmt(r['depth_error_mean'])} | "
                     f"{fmt(r['depth_error_max'])} | {fmt(r['normal_error_deg'])} | "
                     f"{pct(r['capped_fraction'])} |")
        L.append("")
    return "\n".join(L) + "\n"
