"""The search's behaviour as numbers, to show that a change of structure
changed none of it: every library surface, primitives unions, a smooth
union and a blend (the table path), a union written out as text, the seed's
search modes, with camera rays, incoherent rays, any-hit queries and t
windows; per ray, t64, hit, capped, unresolved, iterations and evaluations.

    python -m lgshape.bench.fingerprint --out before.npz
    python -m lgshape.bench.fingerprint --out after.npz --compare before.npz

``--compare`` exits 1 and names each query whose arrays differ in one bit.
"""
from __future__ import annotations

import argparse
import math
import sys

import numpy as np

from .. import primitives as P
from ..surfaces import LIBRARY
from ..trace import Surface

FIELDS = ("t64", "hit", "capped", "unresolved", "iterations", "evals")


def _primitive_models():
    rng = np.random.default_rng(7)
    c = rng.uniform(-0.8, 0.8, (40, 3))
    spheres = P.spheres(c[:20], rng.uniform(0.05, 0.2, 20))
    boxes = P.boxes(c[20:30], rng.uniform(0.05, 0.15, (10, 3)), rounding=0.02)
    tori = P.tori(c[30:], rng.uniform(0.1, 0.2, 10), rng.uniform(0.02, 0.05, 10))
    return {
        "union": (P.union(spheres, boxes, tori), {}),
        "smooth_union": (P.smooth_union(spheres, k=0.1), {}),
        "blend": (P.blend(P.spheres(c[:12], 0.3)), {}),
        "text_min": ("min(" + ", ".join(f"sqrt((x-{a:.4f})^2+(y-{b:.4f})^2+(z-{e:.4f})^2)-0.1"
                                        for a, b, e in c[:16]) + ")",
                     {"bbox": ((-1.1,) * 3, (1.1,) * 3)}),
    }


def surfaces():
    """(name, Surface) for each case."""
    out = [(name, Surface(make())) for name, make in LIBRARY.items()]
    out.append(("sphere/taylor", Surface(LIBRARY["sphere"](), search="taylor")))
    out.append(("torus/global", Surface(LIBRARY["torus"](), search="global")))
    out.append(("blobs/taylor", Surface(LIBRARY["blobs"](), search="taylor")))
    # the rare paths: the edge of f's domain (sqrt), a pole, tangent touches,
    # roots closer than the smallest interval, a root at a domain's edge
    box = ((-1.2,) * 3, (1.2,) * 3)
    out.append(("domain_edge", Surface("sqrt(0.8 - x^2 - y^2) - z^2 - 0.3", box)))
    out.append(("pole", Surface("1 / (x^2 + y^2 + z^2 - 0.25) - 2", box)))
    out.append(("touch", Surface("(x^2 + y^2 + z^2 - 0.5)^2", box)))
    out.append(("near_double", Surface("(x^2 + y^2 + z^2 - 0.5)^2 - 1e-14", box)))
    out.append(("edge_root", Surface("sqrt(0.8 - x^2 - y^2) - 1e-4", box)))
    for name, (model, kw) in _primitive_models().items():
        out.append((name, Surface(model, **kw)))
    return out


def _rays(s: Surface, n: int, seed: int):
    """Camera rays towards the box centre, and incoherent rays from points
    in and around the box (float32)."""
    lo, hi = s.lo, s.hi
    c, ext = 0.5 * (lo + hi), hi - lo
    k = int(math.sqrt(n))
    u, v = np.meshgrid(np.linspace(-0.6, 0.6, k), np.linspace(-0.6, 0.6, k))
    eye = c + np.array([0.3, 0.4, 2.2]) * ext.max()
    target = c + np.stack([u.ravel() * ext[0], v.ravel() * ext[1], np.zeros(k * k)], -1)
    cam_d = target - eye
    rng = np.random.default_rng(seed)
    o = lo - 0.2 * ext + rng.uniform(0, 1.4, (n, 3)) * ext
    d = rng.normal(size=(n, 3))
    return (np.float32(np.broadcast_to(eye, cam_d.shape)), np.float32(cam_d),
            np.float32(o), np.float32(d / np.linalg.norm(d, axis=1, keepdims=True)))


def run(n: int = 1024, seed: int = 3) -> dict:
    """Every query's per-ray arrays, keyed 'surface:query:field'."""
    res = {}
    for name, s in surfaces():
        co, cd, io, idir = _rays(s, n, seed)
        diag = s.diagonal
        w = np.random.default_rng(seed + 1).uniform(0, 1.5 * diag, len(io))
        queries = {
            "camera": (co, cd, {}),
            "incoherent": (io, idir, {}),
            "window": (io, idir, {"t_min": np.float32(0.1 * w), "t_max": np.float32(w)}),
            "any_hit": (io, idir, {"t_max": np.float32(w), "any_hit": True}),
        }
        for q, (o, d, kw) in queries.items():
            r = s.trace(o, d, **kw)
            for f in FIELDS:
                res[f"{name}:{q}:{f}"] = np.asarray(getattr(r, f))
        print(f"{name}: {sum(int(np.asarray(res[f'{name}:{q}:hit']).sum()) for q in queries)} hits",
              file=sys.stderr)
    return res


def compare(a: dict, b: dict) -> list[str]:
    """The keys whose arrays differ in any bit (or are in one only)."""
    bad = sorted(set(a) ^ set(b))
    for k in sorted(set(a) & set(b)):
        x, y = np.asarray(a[k]), np.asarray(b[k])
        if x.shape != y.shape or x.dtype != y.dtype or x.tobytes() != y.tobytes():
            bad.append(k)
    return bad


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m lgshape.bench.fingerprint",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, help="the .npz to write")
    ap.add_argument("--compare", help="an .npz from an earlier run to compare with")
    ap.add_argument("--rays", type=int, default=1024, help="rays per query (default 1024)")
    args = ap.parse_args(argv)
    res = run(args.rays)
    np.savez_compressed(args.out, **res)
    if args.compare:
        with np.load(args.compare) as old:
            bad = compare(dict(old), res)
        for k in bad:
            print(f"differs: {k}")
        print(f"{len(res) - len(bad)} of {len(res)} arrays identical")
        return 1 if bad else 0
    return 0


if __name__ == "__main__":
    sys.exit(main())
