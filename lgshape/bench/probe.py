"""The first-image latency probe of the speed section
(:func:`lgshape.bench.speed.bench_compile`), run in a fresh process:

    python -m lgshape.bench.probe SCENE RES SPP VARIANT

loads the scene and renders it three times at RES x RES pixels, SPP
samples per pixel, on the Mitsuba VARIANT; prints the times (the import of
Dr.Jit and Mitsuba, the scene's load, each render) and Dr.Jit's kernel
history of the renders as one JSON line. This module imports nothing heavy
at its top, so that the imports it times are those of a first image.
"""
from __future__ import annotations

import json
import os
import sys
import time

from ..plugins import use_variant


def probe(scene_path, res, spp, variant):
    """In this process (a fresh one): load the scene, render it three times
    at ``spp`` on ``variant``; the times."""
    t0 = time.perf_counter()
    import drjit as dr                  # inside the timing: the imports are part of the latency
    mi = use_variant(variant)
    t_import = time.perf_counter() - t0
    t0 = time.perf_counter()
    scene = mi.load_file(scene_path, resx=str(res), resy=str(res), spp=str(spp))
    t_load = time.perf_counter() - t0
    times, kernels = [], []
    for _ in range(3):
        dr.kernel_history()                              # clears it
        with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
            t0 = time.perf_counter()
            img = mi.render(scene, spp=spp, seed=0)
            dr.eval(img)
            dr.sync_thread()
            times.append(time.perf_counter() - t0)
        kernels.append([k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT])
    first = kernels[0]
    cache = os.path.join(os.path.expanduser("~"), ".drjit")
    files = os.listdir(cache) if os.path.isdir(cache) else []
    ms = 1e-3
    return {"import_s": t_import, "load_s": t_load, "first_s": times[0], "second_s": times[1],
            "third_s": times[2], "cache_files": len(files),
            "kernels": len(first),
            "kernels_compiled": sum(1 for k in first if not k["cache_hit"] and not k["cache_disk"]),
            "kernels_from_disk": sum(1 for k in first if not k["cache_hit"] and k["cache_disk"]),
            "backend_s": ms * sum(k.get("backend_time", 0.0) for k in first),
            "codegen_s": ms * sum(k.get("codegen_time", 0.0) for k in first),
            "execution_s": ms * sum(k.get("execution_time", 0.0) for k in first),
            "second_codegen_s": ms * sum(k.get("codegen_time", 0.0) for k in kernels[1]),
            "ir_ops": max((k.get("operation_count", 0) for k in first), default=0)}


if __name__ == "__main__":
    scene, res, spp, variant = sys.argv[1:5]
    print(json.dumps(probe(scene, int(res), int(spp), variant)))
