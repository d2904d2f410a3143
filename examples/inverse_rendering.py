"""Inverse rendering with lgshape: recover shape, light, medium and colour
parameters from a target image.

Five problems (the first argument):

- ``torus``: a library torus's two radii and its albedo (target R = 0.75,
  r = 0.28, albedo (0.7, 0.35, 0.2); start R = 0.6, r = 0.2, grey);
- ``blobs``: a primitives model, three blended blobs (Wyvill's kernel,
  written as an expression whose named constants are the centres): the
  x and y of each centre (start: each moved by about 0.1);
- ``light``: the radius of an emitting lgsurface sphere out of view, from
  the light and the shadow it casts on a floor and a ball (target 0.15,
  start 0.08; the gradient is the light's interior and edge terms);
- ``fog``: the density (``sigma_t``) of a homogeneous fog inside a torus
  with a ``null`` surface, from its image against a sky (target 2.0,
  start 0.7), rendered with ``lg_prbvolpath``;
- ``fogshape``: the tube radius of that fog torus (density 2.0; target
  r = 0.3, start 0.22), from the same view, under ``lg_prbvolpath`` (the
  shape of a ``null`` surface around a homogeneous medium).

The target is rendered with lg_path (lg_volpath for the fogs) at
``--target-spp`` samples per pixel (default: 32 times ``--spp``, 512 at the
default 16); the optimisation runs mi.ad.Adam on the L2 image loss,
rendering with lg_prb (interior, silhouette, shadow-edge and light-edge
gradients; lg_prbvolpath for the fogs), the learning rate decaying after the
first 60 iterations. It writes, into the output folder, the target, the first and
the last image (EXR, the last at the target's spp), the loss curve
(loss.png) and the parameters per iteration (history.json), and prints each
parameter's relative error (in units of the blob radius for the blobs),
then its verdict: ``converged`` where every error is within
``--tolerance`` (default 1%), exit status 0; else ``did not converge``,
naming the parameters outside it, exit status 1 (2: bad arguments).

    python examples/inverse_rendering.py torus [--iterations 200] [--out inverse-torus]
    python examples/inverse_rendering.py blobs [--iterations 200] [--out inverse-blobs]
    python examples/inverse_rendering.py light [--iterations 200] [--out inverse-light]
    python examples/inverse_rendering.py fog [--iterations 200] [--out inverse-fog]
    python examples/inverse_rendering.py fogshape [--iterations 200] [--out inverse-fogshape]
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import drjit as dr
import mitsuba as mi
import numpy as np

import lgshape

RADIUS = 0.45          # the blobs' radius of influence
BLOBS = "0.3 - " + " - ".join(
    f"max(0, 1 - ((x - {c}x)^2 + (y - {c}y)^2 + (z - {z})^2) / {RADIUS ** 2})^3"
    for c, z in (("a", 0.0), ("b", 0.1), ("c", -0.1)))


def torus(R, r, albedo):
    # a box of its own that holds every torus on the way: a box that moved
    # with R and r would change the scene's bounds, which the sky (Mitsuba's
    # constant emitter) compiles into its kernels
    return {"type": "lgsurface", "surface": "torus", "R": R, "r": r,
            "bbox_min": [-1.4, -1.4, -0.6], "bbox_max": [1.4, 1.4, 0.6],
            "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], 55),
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": albedo}}}


def blobs(ax, ay, bx, by, cx, cy):
    return {"type": "lgsurface", "expr": BLOBS, "ax": ax, "ay": ay, "bx": bx, "by": by,
            "cx": cx, "cy": cy, "bbox_min": [-1.2, -1.2, -0.7], "bbox_max": [1.2, 1.2, 0.7],
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb",
                                                        "value": [0.3, 0.5, 0.8]}}}


def lamp(r):
    """An emitting sphere out of view (its box holds every radius on the
    way, so that the scene's bounds stay put)."""
    return {"type": "lgsurface", "expr": "x^2 + y^2 + z^2 - r^2", "r": r,
            "bbox_min": [-0.4] * 3, "bbox_max": [0.4] * 3,
            "to_world": mi.ScalarTransform4f().translate([0.3, 1.6, -0.2]),
            "bsdf": {"type": "diffuse"},
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 12.0}}}


def fog_torus(sigma_t, r=0.3):
    return {"type": "lgsurface", "surface": "torus", "R": 0.7, "r": r,
            "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], 60),
            "bsdf": {"type": "null"},
            "interior": {"type": "homogeneous", "sigma_t": sigma_t,
                         "albedo": {"type": "rgb", "value": 0.8}}}


def sensor(eye, fov, res, spp):
    return {"type": "perspective", "fov": fov,
            "to_world": mi.ScalarTransform4f().look_at(eye, [0, 0, 0], [0, 1, 0]),
            "film": {"type": "hdrfilm", "width": res, "height": res,
                     "rfilter": {"type": "box"}},
            "sampler": {"type": "independent", "sample_count": spp}}


def lit_shape(view):
    """The torus's and the blobs' scene: the shape under a sky and the sun,
    seen from view["eye"]; lg_prb's silhouette band and shadow edges as
    the view says."""
    def build(integrator, shape, res, spp):
        extra = ({"band_width": view["band_width"], "shadow_edges": view["shadow_edges"]}
                 if integrator == "lg_prb" else {})
        return {"type": "scene", "integrator": {"type": integrator, "max_depth": 3, **extra},
                "sensor": sensor(view["eye"], view["fov"], res, spp),
                "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 0.25}},
                "sun": {"type": "directional", "direction": list(view["sun"]),
                        "irradiance": {"type": "rgb", "value": 2.5}},
                "obj": shape}
    return build


def lit_floor(integrator, shape, res, spp):
    """The light problem's scene: a floor and a grey ball in view, lit only
    by the lamp (``shape``, out of view; direct light: max_depth 2)."""
    return {"type": "scene", "integrator": {"type": integrator, "max_depth": 2},
            "sensor": sensor((0, 2.2, 2.2), 40, res, spp),
            "floor": {"type": "rectangle",
                      "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.8}},
                      "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90)
                      @ mi.ScalarTransform4f().scale(3)},
            "ball": {"type": "sphere", "radius": 0.3, "center": [0, 0.3, 0],
                     "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.5}}},
            "lamp": shape}


def fog_sky(integrator, shape, res, spp):
    """The fog problem's scene: the fog torus (``shape``) against a sky."""
    return {"type": "scene", "integrator": {"type": integrator, "max_depth": 8},
            "sensor": sensor((0, 0.3, 3), 40, res, spp),
            "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
            "obj": shape}


#: name -> the problem: ``shape`` (builder of the object whose parameters
#: are optimised), ``scene`` (builder of the scene around it, given the
#: integrator), the ``true`` and ``start`` values, the error ``scale``
#: (None for relative errors, else a length the errors are measured in),
#: the ``primal`` and ``gradient`` integrators, each parameter's bounds
#: (``clip``) and Adam's default learning rate. The torus's and the blobs'
#: view: the camera, the sun (for the blobs about the view's direction, so
#: that the shadows they cast on each other stay mostly behind them) and
#: lg_prb's silhouette band (its bias grows with the band's width against
#: the silhouette's curvature radius, in pixels: the blobs are small, so
#: their band is half a pixel) and whether it adds the shadow edges' term:
#: not for the blobs, where the edges of the sky's shadows on them, correct
#: but noisy in a band of half a pixel, keep Adam from settling within 1% in
#: 200 iterations (measured: 1.35% at the end) while their shadows on each
#: other fall behind them.
PROBLEMS = {
    "torus": {"shape": torus, "true": {"obj.R": 0.75, "obj.r": 0.28,
                                       "obj.bsdf.reflectance.value": (0.7, 0.35, 0.2)},
              "start": {"obj.R": 0.6, "obj.r": 0.2,
                        "obj.bsdf.reflectance.value": (0.5, 0.5, 0.5)},
              "scale": None, "primal": "lg_path", "gradient": "lg_prb", "lr": 0.02,
              "clip": {"obj.R": (0.05, 2.0), "obj.r": (0.05, 2.0),
                       "obj.bsdf.reflectance.value": (0.0, 1.0)},
              "scene": lit_shape({"eye": (0, -0.6, 4), "fov": 35, "sun": (0.4, 0.5, -1.0),
                                  "band_width": 1.0, "shadow_edges": True})},
    "blobs": {"shape": blobs, "true": {"obj.ax": -0.35, "obj.ay": -0.1, "obj.bx": 0.35,
                                       "obj.by": -0.05, "obj.cx": 0.0, "obj.cy": 0.3},
              "start": {"obj.ax": -0.25, "obj.ay": -0.18, "obj.bx": 0.42, "obj.by": 0.05,
                        "obj.cx": 0.08, "obj.cy": 0.22},
              "scale": RADIUS, "primal": "lg_path", "gradient": "lg_prb", "lr": 0.02,
              "clip": {k: (-1.0, 1.0) for k in ("obj.ax", "obj.ay", "obj.bx", "obj.by",
                                                "obj.cx", "obj.cy")},
              "scene": lit_shape({"eye": (0, -0.3, 2.4), "fov": 40, "sun": (0.05, 0.1, -1.0),
                                  "band_width": 0.5, "shadow_edges": False})},
    "light": {"shape": lamp, "true": {"lamp.r": 0.15}, "start": {"lamp.r": 0.08},
              "scale": None, "primal": "lg_path", "gradient": "lg_prb", "lr": 0.01,
              "clip": {"lamp.r": (0.02, 0.35)}, "scene": lit_floor},
    "fog": {"shape": fog_torus, "true": {"obj.interior_medium.sigma_t.value.value": 2.0},
            "start": {"obj.interior_medium.sigma_t.value.value": 0.7},
            "scale": None, "primal": "lg_volpath", "gradient": "lg_prbvolpath", "lr": 0.05,
            "clip": {"obj.interior_medium.sigma_t.value.value": (0.05, 20.0)}, "scene": fog_sky},
    "fogshape": {"shape": lambda r: fog_torus(2.0, r), "true": {"obj.r": 0.3},
                 "start": {"obj.r": 0.22}, "scale": None, "primal": "lg_volpath",
                 "gradient": "lg_prbvolpath", "lr": 0.01, "clip": {"obj.r": (0.05, 0.6)},
                 "scene": fog_sky},
}


def scene(problem, integrator, values, res, spp):
    """The problem's scene with its object built from ``values``, rendered
    by ``integrator``."""
    return mi.load_dict(problem["scene"](integrator, problem["shape"](*values), res, spp))


def values(params, keys):
    """The parameters' current values (floats, or tuples for colours)."""
    out = []
    for k in keys:
        v = np.array(params[k], np.float64).ravel()
        out.append(tuple(v.tolist()) if v.size > 1 else float(v[0]))
    return out


def errors(params, true, scale):
    """Each optimised parameter's error (the worst channel): relative, or
    in units of ``scale``."""
    out = {}
    for k, t in true.items():
        v = np.array(params[k], np.float64).ravel()
        t = np.array(t, np.float64).ravel()
        out[k] = float(np.max(np.abs(v - t) / (np.abs(t) if scale is None else scale)))
    return out


def positive(kind):
    """An argparse type: a number of ``kind`` above 0."""
    def parse(text):
        v = kind(text)
        if not v > 0:
            raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
        return v
    return parse


class Defaults(argparse.ArgumentDefaultsHelpFormatter):
    """--help shows each option's default (where it has one: an option
    whose default is worked out, None here, says so in its own help)."""
    def _get_help_string(self, action):
        return action.help if action.default is None else super()._get_help_string(action)


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=Defaults,
        epilog="Exit status: 0 converged (every parameter within --tolerance of the truth), "
               "1 did not converge, 2 bad arguments.")
    ap.add_argument("problem", choices=sorted(PROBLEMS),
                    help="torus: a library torus's radii and albedo; blobs: three blobs' "
                         "centres; light: an emitting sphere's radius; fog: a fog's density; "
                         "fogshape: the fog torus's tube radius")
    ap.add_argument("--iterations", type=positive(int), default=200, help="Adam iterations")
    ap.add_argument("--res", type=positive(int), default=48, help="image width and height")
    ap.add_argument("--spp", type=positive(int), default=16,
                    help="samples per pixel per iteration")
    ap.add_argument("--target-spp", type=positive(int), default=None,
                    help="samples per pixel of the target and the final image "
                         "(default: 32 x --spp)")
    ap.add_argument("--lr", type=positive(float), default=None,
                    help="Adam's learning rate (default: the problem's, 0.01 to 0.05)")
    ap.add_argument("--tolerance", type=positive(float), default=0.01,
                    help="the largest error that counts as converged (0.01: 1%%)")
    ap.add_argument("--out", default=None, help="output folder (default: inverse-PROBLEM)")
    ap.add_argument("--variant", default="llvm_ad_rgb", help="Mitsuba variant")
    return ap


def verdict(err, tolerance, unit, iterations):
    """(text, exit status): 'converged' where every error is within
    ``tolerance``, else 'did not converge' naming those beyond it."""
    worse = {k: e for k, e in err.items() if not e <= tolerance}
    if not worse:
        return (f"converged: every parameter within {100 * tolerance:g}% ({unit})", 0)
    return (f"did not converge: after {iterations} iterations "
            + ", ".join(f"{k} is off by {100 * e:.2f}%" for k, e in worse.items())
            + f" ({unit}; tolerance {100 * tolerance:g}%); try more --iterations", 1)


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    target_spp = args.target_spp or 32 * args.spp
    mi.set_variant(args.variant)
    lgshape.register_plugins()
    problem = PROBLEMS[args.problem]
    true, start, scale = problem["true"], problem["start"], problem["scale"]
    out = args.out or f"inverse-{args.problem}"
    os.makedirs(out, exist_ok=True)

    target = mi.render(scene(problem, problem["primal"], true.values(), args.res, target_spp),
                       seed=12345)
    mi.util.write_bitmap(os.path.join(out, "target.exr"), target)

    s = scene(problem, problem["gradient"], start.values(), args.res, args.spp)
    params = mi.traverse(s)
    lr = args.lr or problem["lr"]
    opt = mi.ad.Adam(lr=lr)
    for k in true:
        opt[k] = params[k]
    params.update(opt)
    history = []
    t0 = time.perf_counter()
    for it in range(args.iterations):
        opt.set_learning_rate(lr * 0.985 ** max(0, it - 60))
        img = mi.render(s, params, seed=2 * it, seed_grad=2 * it + 1)
        if it == 0:
            mi.util.write_bitmap(os.path.join(out, "start.exr"), img)
        loss = dr.mean(dr.square(img - target), axis=None)
        dr.backward(loss)
        opt.step()
        for k in true:                         # radii positive, colours in [0, 1], ...
            opt[k] = dr.clip(opt[k], *problem["clip"][k])
        params.update(opt)
        rec = {"iteration": it, "loss": float(np.array(loss).ravel()[0]),
               **dict(zip(true, values(params, true)))}
        history.append(rec)
        if it % 20 == 0 or it == args.iterations - 1:
            err = errors(params, true, scale)
            print(f"iteration {it:4d}: loss {rec['loss']:.3e}, "
                  + ", ".join(f"{[n for n in k.split('.') if n != 'value'][-1]} {100 * e:.2f}%"
                            for k, e in err.items()),
                  file=sys.stderr, flush=True)
    seconds = time.perf_counter() - t0
    final = mi.render(scene(problem, problem["primal"], values(params, true), args.res,
                            target_spp), seed=12345)
    mi.util.write_bitmap(os.path.join(out, "final.exr"), final)
    err = errors(params, true, scale)
    with open(os.path.join(out, "history.json"), "w") as fh:
        json.dump({"problem": args.problem, "true": true, "start": start, "seconds": seconds,
                   "spp": args.spp, "target_spp": target_spp, "tolerance": args.tolerance,
                   "errors": err, "history": history}, fh, indent=1)
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        fig, ax = plt.subplots(figsize=(5, 3.2))
        ax.semilogy([h["loss"] for h in history])
        ax.set_xlabel("iteration")
        ax.set_ylabel("image L2 loss")
        fig.tight_layout()
        fig.savefig(os.path.join(out, "loss.png"), dpi=120)
    except ImportError:
        print("matplotlib missing: no loss.png (pip install matplotlib)", file=sys.stderr)
    unit = "relative errors" if scale is None else f"errors in units of {scale:g}"
    print(f"{args.iterations} iterations in {seconds:.1f} s; {unit}: "
          + ", ".join(f"{k}: {100 * e:.2f}%" for k, e in err.items()))
    text, status = verdict(err, args.tolerance, unit, args.iterations)
    print(text)
    return status


if __name__ == "__main__":
    sys.exit(main())
