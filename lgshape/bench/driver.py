"""``lgshape bench [--quick] --out DIR``: runs the benchmark's sections and
writes DIR/results.json, DIR/charts/ and DIR/BENCHMARKS.md.

The sections, in order: accuracy on primary rays and the stability suite
(:mod:`lgshape.bench.accuracy`), speed (:mod:`lgshape.bench.speed`), scale
(:mod:`lgshape.bench.scale`), temporal stability
(:mod:`lgshape.bench.temporal`) and conformance against Mitsuba's
integrators (:mod:`lgshape.bench.conformance`); the report and the accuracy charts come
from :mod:`lgshape.bench.report`.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
import time

from . import stability
from ..surfaces import LIBRARY
from . import conformance, projective, scale, speed, temporal
from .accuracy import (DEFAULT_LG, FULL, QUICK, accuracy_subset, bench_surface,
                       stability_runners)
from .common import VARIANT, finite, git_commit, machine, stderr_log
from .report import charts, report


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="lgshape bench", description="lgshape against sphere tracing, marching, Mitsuba's "
        "sdfgrid and a marching-cubes mesh: speed against accuracy, and a stability suite.")
    p.add_argument("--quick", action="store_true",
                   help="a smoke run of well under a minute: fewer rays and settings")
    p.add_argument("--out", required=True, help="output folder (results.json, charts/, "
                   "BENCHMARKS.md)")
    p.add_argument("--surfaces", nargs="+", choices=sorted(LIBRARY), metavar="NAME",
                   help="only these library surfaces")
    p.add_argument("--variant", default=VARIANT,
                   help=f"the Mitsuba variant, a JIT one (default {VARIANT}; cuda_ad_rgb on a "
                   "GPU): the speed and conformance sections render with it, the ray queries "
                   "run on its backend")
    p.add_argument("--no-stability", dest="stability", action="store_false",
                   help="skip the stability suite")
    p.add_argument("--no-speed", dest="speed", action="store_false",
                   help="skip the speed section (camera, incoherent and shadow rays against the "
                   "sphere tracer and the mesh; the Cornell render and its gradient pass; "
                   "compile latency)")
    p.add_argument("--no-scale", dest="scale", action="store_false",
                   help="skip the scale section (cost against the number of primitives)")
    p.add_argument("--no-temporal", dest="temporal", action="store_false",
                   help="skip the temporal-stability section (animation)")
    p.add_argument("--no-conformance", dest="conformance", action="store_false",
                   help="skip the conformance section (the lg integrators against Mitsuba's, "
                   "pixel by pixel, on scenes with native twins)")
    p.add_argument("--no-projective", dest="projective", action="store_false",
                   help="skip the gradients section (lg_prb on implicit surfaces against "
                   "Mitsuba's prb_projective on their marching-cubes meshes: error against "
                   "finite differences, standard error, cost of the gradient pass)")
    return p


def main(argv=None) -> int:
    """``lgshape bench ARGS`` (``argv``: ARGS; default sys.argv[1:])."""
    argv = list(sys.argv[1:] if argv is None else argv)
    args = _parser().parse_args(argv)
    cfg = QUICK if args.quick else FULL
    surfaces = tuple(args.surfaces) if args.surfaces else cfg.surfaces
    from ..plugins import VariantError, use_variant     # (imports Mitsuba: heavy)
    try:
        use_variant(args.variant)
    except VariantError as err:
        print(f"lgshape bench: error: {err}", file=sys.stderr)
        return 2
    command = "lgshape bench " + " ".join(argv)
    t_start = time.perf_counter()
    log = stderr_log(t_start)
    now = datetime.datetime.now().astimezone()
    meta = {"command": command, "date": now.isoformat(timespec="seconds"),
            "machine": machine(), "git": git_commit(), "quick": bool(args.quick), "res": cfg.res,
            "repeats": cfg.repeats, "min_sample": cfg.min_sample, "stride": cfg.stride,
            "accuracy_rays": len(accuracy_subset(cfg.res, cfg.stride)),
            "scan_steps": cfg.scan_steps, "variant": args.variant,
            "depth_error_unit": "box diagonals", "normal_error_unit": "degrees, between lines",
            "stability_tolerance": stability.TOLERANCE}
    records = []
    for name in surfaces:
        records += bench_surface(name, cfg, log)
    stab, notes = stability.run(
        stability.cases(scale=cfg.stability_scale),
        lambda case, rays: stability_runners(case.surface, rays, cfg, case.lipschitz),
        log) if args.stability else ([], [])
    results = {"meta": meta, "records": records, "stability": stab, "cases": notes}
    os.makedirs(os.path.join(args.out, "charts"), exist_ok=True)
    if args.speed:
        results["speed"] = speed.run(log, quick=args.quick,
                                     surfaces=tuple(args.surfaces) if args.surfaces else None,
                                     variant=args.variant)
        speed.chart(results["speed"], os.path.join(args.out, "charts", "speed.png"))
    if args.scale:
        results["scale"] = scale.run(log, quick=args.quick, res=cfg.res, repeats=cfg.repeats)
        scale.chart(results["scale"], os.path.join(args.out, "charts", "scale.png"))
    if args.temporal:
        results["temporal"] = temporal.run(log, quick=args.quick)
        temporal.chart(results["temporal"], os.path.join(args.out, "charts", "temporal.png"))
    if args.conformance:
        results["conformance"] = conformance.run(log, quick=args.quick)
    if args.projective:
        results["projective"] = projective.run(log, quick=args.quick)
    written = charts(records, args.out)
    results["meta"]["seconds"] = round(time.perf_counter() - t_start, 1)
    with open(os.path.join(args.out, "results.json"), "w") as fh:
        json.dump(finite(results), fh, indent=1, allow_nan=False)
    with open(os.path.join(args.out, "BENCHMARKS.md"), "w") as fh:
        sections = [speed.report(results["speed"]) if results.get("speed") else [],
                    scale.report(results["scale"], meta["res"]) if results.get("scale") else [],
                    temporal.report(results["temporal"]) if results.get("temporal") else [],
                    conformance.report(results["conformance"])
                    if results.get("conformance") else [],
                    projective.report(results["projective"])
                    if results.get("projective") else []]
        fh.write(report(results, command, written, sections, DEFAULT_LG))
    log(f"wrote {os.path.join(args.out, 'results.json')}, BENCHMARKS.md and {len(written)} charts")
    return 0

