"""lgshape's ray kernel alone against a global-bound sphere tracer.

For 1024 x 1024 primary rays through each library surface (a fixed camera,
lgshape.camera), prints Mrays/s (median of repeats, measured in this run) and
the mean / max function evaluations per ray (an interval evaluation counts
one), the pruning structure's memory, the rays that reached the iteration
bound, and the pixels where the two disagree on hit / miss (with a float64
brute-force verdict on who is right, on up to 4096 of them). Run:
python -m lgshape.bench.trace_speed [--res 1024] [--repeats 3] [surface ...]
"""
import argparse
import time

import drjit as dr
import numpy as np
from drjit.llvm.ad import Array3f

from .. import bounds, camera
from ..expr import evaluate
from ..reference import clip_to_box, first_sign_change
from ..surfaces import LIBRARY
from ..trace import Surface
from .baselines import sphere_trace


def timed(fn, repeats):
    times, out = [], None
    for _ in range(repeats + 1):                # the first run compiles
        t = time.perf_counter()
        out = fn()
        dr.eval(out.t, out.hit, out.evals, out.capped)
        dr.sync_thread()
        times.append(time.perf_counter() - t)
    return out, float(np.median(times[1:]))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("surfaces", nargs="*", default=sorted(LIBRARY))
    ap.add_argument("--res", type=int, default=1024)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--depth", type=int, default=None, help="pruning depth (default: lgshape's)")
    ap.add_argument("--search", default=None, help="search mode (default: lgshape's)")
    args = ap.parse_args()
    n = args.res ** 2
    print(f"{'surface':13} {'method':14} {'Mrays/s':>8} {'evals':>6} {'max':>6} {'capped':>6} "
          f"{'mem KiB':>8} {'speedup':>7}  disagreements (float64 says)")
    for name in args.surfaces:
        spec = LIBRARY[name]()
        surf = Surface(spec, depth=args.depth, search=args.search)
        o_np, d_np = camera.primary_rays(spec.bbox, args.res)
        o, d = Array3f(o_np.T.copy()), Array3f(d_np.T.copy())
        dr.eval(o, d)
        L = float(bounds.lipschitz(spec.expr, surf.lo[None], surf.hi[None])[0])
        lg, t_lg = timed(lambda: surf.trace(o, d), args.repeats)
        st, t_st = timed(lambda: sphere_trace(surf, o, d, L), args.repeats)
        h_lg, h_st = np.asarray(lg.hit), np.asarray(st.hit)
        # Who is right where they disagree: float64 brute force (8192 steps).
        dis_all = np.flatnonzero(h_lg != h_st)
        # At most 4096 of them, sampled, get the (costly) float64 verdict.
        dis = np.random.default_rng(0).choice(dis_all, min(len(dis_all), 4096), replace=False)
        verdict = ""
        if len(dis):
            oo, dd = o_np[dis].astype(np.float64), d_np[dis].astype(np.float64)
            t0, t1 = clip_to_box(oo, dd, surf.lo, surf.hi)

            def F(X, Y, Z):
                return evaluate(spec.expr, {"x": X, "y": Y, "z": Z})
            ref = np.concatenate([np.isfinite(first_sign_change(F, oo[k:k + 1024], dd[k:k + 1024],
                                                                t0[k:k + 1024], t1[k:k + 1024], steps=8192))
                                  for k in range(0, len(dis), 1024)])
            lg_right = (h_lg[dis] == ref).sum()
            verdict = (f"{len(dis_all)} px; of {len(dis)} checked, lgshape right on {lg_right}, "
                       f"sphere tracer on {len(dis) - lg_right}")
        for label, r, t in (("lgshape", lg, t_lg), ("sphere-trace", st, t_st)):
            ev = np.asarray(r.evals, np.float64)
            print(f"{name:13} {label:14} {n / t / 1e6:8.2f} {ev.mean():6.1f} {ev.max():6.0f} "
                  f"{int(np.asarray(r.capped).sum()):6d} "
                  f"{(surf.memory_bytes / 1024 if label == 'lgshape' else 0):8.0f} "
                  f"{(t_st / t if label == 'lgshape' else 1.0):7.2f}  "
                  f"{verdict if label == 'lgshape' else ''}", flush=True)


if __name__ == "__main__":
    main()
