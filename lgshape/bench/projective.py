"""Gradients of lg_prb on implicit surfaces against Mitsuba's
``prb_projective`` on a marching-cubes mesh of the same surface.

Each scene (:data:`SCENES`) is rendered twice: once with the lgsurface
and ``lg_prb``, once with a marching-cubes mesh of the same surface
(scikit-image's, of a grid of samples of a distance-like function of the
surface over its box) and ``prb_projective``. The shape parameter reaches
the mesh through its vertices: each vertex is an analytic, differentiable
function of the parameter (``v(p) = v0 + (p - p0) dv/dp``, dv/dp the
surface's own motion at that vertex: radial for a torus's major radius,
from the centre for a sphere's radius), written into the mesh's
``vertex_positions`` with ``mi.traverse``.

Per scene and integrator (:func:`measure`):

- the AD estimate of d mean(image) / d p (``dr.backward`` of the image
  mean) at a low spp over ``seeds`` independent seeds: the mean and its
  standard error (std / sqrt(seeds)); the per-seed standard deviation is
  the standard error of one estimate at that spp;
- the central finite difference (step h) of the same scene's primal
  image mean at a large spp, over ``fd_seeds`` seeds (the two sides of each
  difference share their seed), with its standard error; the mesh's FD is
  its own (the estimator prb_projective differentiates), and the
  difference between the two scenes' FDs is the mesh's discretization;
- the error of the AD mean against its scene's FD, and that error in units
  of their combined standard error (z);
- the time of one gradient pass (render with the parameter attached, then
  ``dr.backward``, evaluated) against one primal render at the same spp:
  medians over the seeds after the first (which compiles).

- the same two times at a larger image (``time_res``), where neither pass
  is launch-bound.

Targets per scene (:func:`targets`): lg_prb's |error vs FD| <= prb_projective's
(or within 2 combined standard errors of zero, where both are noise), its
per-estimate standard error <= 2x prb_projective's, its gradient pass <= 3x
its primal (at ``time_res``).
"""
from __future__ import annotations

import os
import tempfile
import time
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ProjectiveConfig:
    res: int = 32           #: image side (pixels)
    spp: int = 32           #: spp of each AD estimate
    seeds: int = 32         #: independent AD estimates (an sd from 8 is +-27%)
    fd_spp: int = 1024      #: spp of each primal render of the FD
    fd_seeds: int = 4       #: independent FDs
    grid: int = 96          #: marching-cubes samples per axis
    scenes: tuple = ("torus", "sphere_shadow")
    time_res: int = 128     #: image side of the timing at size (0: none)
    time_reps: int = 3      #: gradient passes and primals timed there


QUICK = ProjectiveConfig()
FULL = ProjectiveConfig(spp=64, seeds=32, fd_spp=4096, fd_seeds=8, grid=160, time_res=256)

TORUS_TILT = 55.0           # degrees about x (the inverse-rendering example's)
SPHERE_C = np.array([0.0, 0.0, 0.45])


def _rot_x(deg):
    a = np.radians(deg)
    return np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])


# ---- the surfaces: the lgsurface, a sampled function for marching cubes, the
#      vertices' motion ---------------------------------------------------------

def _torus_lg(p, r=0.28):
    import mitsuba as mi
    return {"type": "lgsurface", "surface": "torus", "R": p, "r": r,
            "bbox_min": [-1.4, -1.4, -0.6], "bbox_max": [1.4, 1.4, 0.6],
            "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], TORUS_TILT)}


def _torus_mesh(p, grid, r=0.28):
    """Vertices (world), faces and dv/dR (world) of the torus's mesh."""
    from skimage.measure import marching_cubes
    lo, hi = np.array([-1.4, -1.4, -0.6]), np.array([1.4, 1.4, 0.6])
    ax = [np.linspace(lo[i], hi[i], grid) for i in range(3)]
    X, Y, Z = np.meshgrid(*ax, indexing="ij")
    f = (np.sqrt(X ** 2 + Y ** 2) - p) ** 2 + Z ** 2 - r ** 2
    v, faces, _, _ = marching_cubes(f, 0.0, spacing=tuple((hi - lo) / (grid - 1)))
    v = v + lo
    rho = np.sqrt(v[:, 0] ** 2 + v[:, 1] ** 2)
    d = np.stack([v[:, 0] / rho, v[:, 1] / rho, np.zeros_like(rho)], 1)
    M = _rot_x(TORUS_TILT)
    return v @ M.T, faces, d @ M.T


def _sphere_lg(p):
    c = SPHERE_C
    return {"type": "lgsurface", "expr": f"x^2 + y^2 + (z - {c[2]})^2 - r^2", "r": p,
            "bbox_min": [-0.7, -0.7, c[2] - 0.7], "bbox_max": [0.7, 0.7, c[2] + 0.7]}


def _sphere_mesh(p, grid):
    from skimage.measure import marching_cubes
    c = SPHERE_C
    lo, hi = c - 0.7, c + 0.7
    ax = [np.linspace(lo[i], hi[i], grid) for i in range(3)]
    X, Y, Z = np.meshgrid(*ax, indexing="ij")
    f = np.sqrt((X - c[0]) ** 2 + (Y - c[1]) ** 2 + (Z - c[2]) ** 2) - p
    v, faces, _, _ = marching_cubes(f, 0.0, spacing=tuple((hi - lo) / (grid - 1)))
    v = v + lo
    return v, faces, (v - c) / p


#: name -> (what, lgsurface(p), mesh(p, grid), parameter key of the
#: lgsurface, p, FD step h, the view)
SCENES = {
    "torus": ("inverse-rendering example's torus, d mean / d R (major radius)",
              _torus_lg, _torus_mesh, "obj.R", 0.75, 1e-2,
              {"eye": (0, -0.6, 4), "target": (0, 0, 0), "fov": 35, "sky": 0.25,
               "sun": (0.4, 0.5, -1.0), "floor": False, "band_width": 1.0}),
    "sphere_shadow": ("sphere on a floor under a point light, d mean / d radius "
                      "(silhouette + shadow)",
                      _sphere_lg, _sphere_mesh, "obj.r", 0.4, 1e-2,
                      {"eye": (0, -3.0, 2.2), "target": (0, 0, 0.3), "fov": 40, "sky": 0.1,
                       "point": (0.8, -0.6, 2.2), "floor": True, "band_width": 1.0}),
}


def _scene(integrator, shape, view, res, spp):
    import mitsuba as mi
    T = mi.ScalarTransform4f()
    extra = ({"band_width": view["band_width"], "shadow_edges": True}
             if integrator == "lg_prb" else {})
    d = {"type": "scene", "integrator": {"type": integrator, "max_depth": 3, **extra},
         "sensor": {"type": "perspective", "fov": view["fov"],
                    "to_world": T.look_at(view["eye"], view["target"], [0, 1, 0]),
                    "film": {"type": "hdrfilm", "width": res, "height": res,
                             "rfilter": {"type": "box"}},
                    "sampler": {"type": "independent", "sample_count": spp}},
         "sky": {"type": "constant", "radiance": {"type": "rgb", "value": view["sky"]}},
         "obj": {**shape, "bsdf": {"type": "diffuse",
                                   "reflectance": {"type": "rgb", "value": [0.7, 0.35, 0.2]}}}}
    if "sun" in view:
        d["sun"] = {"type": "directional", "direction": list(view["sun"]),
                    "irradiance": {"type": "rgb", "value": 2.5}}
    if "point" in view:
        d["light"] = {"type": "point", "position": list(view["point"]),
                      "intensity": {"type": "rgb", "value": 6.0}}
    if view["floor"]:
        d["floor"] = {"type": "rectangle", "to_world": T.scale(3.0),
                      "bsdf": {"type": "diffuse",
                               "reflectance": {"type": "rgb", "value": 0.6}}}
    return mi.load_dict(d)


class _Case:
    """One scene with one integrator: ``set(params, p)`` puts the
    (attached or plain) parameter value p into the scene."""

    def __init__(self, name, kind, cfg, tmpdir, res=None):
        import drjit as dr
        import mitsuba as mi
        what, lg, mesh, key, p0, h, view = SCENES[name]
        self.p0, self.h = p0, h
        res = res or cfg.res
        if kind == "lg_prb":
            self.scene = _scene("lg_prb", lg(p0), view, res, cfg.spp)
            self.faces = None

            def set_(params, p):
                params[key] = p
        else:
            from .common import mitsuba_mesh
            v, faces, dv = mesh(p0, cfg.grid)
            path = os.path.join(tmpdir, f"{name}.ply")
            mitsuba_mesh(v, faces).write_ply(path)
            self.scene = _scene("prb_projective", {"type": "ply", "filename": path},
                                view, res, cfg.spp)
            self.faces = len(faces)
            v0 = mi.Point3f(*(mi.Float(v[:, i].astype(np.float32)) for i in range(3)))
            d = mi.Vector3f(*(mi.Float(dv[:, i].astype(np.float32)) for i in range(3)))

            def set_(params, p):
                params["obj.vertex_positions"] = dr.ravel(v0 + (p - p0) * d)
        self.set = set_

    def primal(self, p, seed, spp):
        import drjit as dr
        import mitsuba as mi
        params = mi.traverse(self.scene)
        self.set(params, mi.Float(p))
        params.update()
        img = mi.render(self.scene, seed=seed, spp=spp)
        return float(np.mean(np.array(img, np.float64)))

    def gradient(self, seed, spp):
        """(d mean / d p by one backward pass, its seconds)."""
        import drjit as dr
        import mitsuba as mi
        t0 = time.perf_counter()
        p = mi.Float(self.p0)
        dr.enable_grad(p)
        params = mi.traverse(self.scene)
        self.set(params, p)
        params.update()
        img = mi.render(self.scene, params, seed=seed, seed_grad=seed + 7919, spp=spp)
        dr.backward(dr.mean(img, axis=None))
        g = dr.grad(p)
        dr.eval(g)
        g = float(g[0])
        return g, time.perf_counter() - t0


def measure(name, kind, cfg: ProjectiveConfig, tmpdir=None) -> dict:
    """The figures of one scene (``name``, :data:`SCENES`) with one
    integrator (``kind``: ``lg_prb`` or ``prb_projective``): see the module
    docstring. Returns a JSON-ready dict."""
    import mitsuba as mi
    with tempfile.TemporaryDirectory() as tmp:
        case = _Case(name, kind, cfg, tmpdir or tmp)
        grads, tg, tp = [], [], []
        for k in range(cfg.seeds):
            g, t = case.gradient(1000 + 2 * k, cfg.spp)
            grads.append(g)
            tg.append(t)
            t0 = time.perf_counter()
            case.primal(case.p0, 1000 + 2 * k, cfg.spp)
            tp.append(time.perf_counter() - t0)
        fds = []
        for k in range(cfg.fd_seeds):
            a = case.primal(case.p0 + case.h, 50 + k, cfg.fd_spp)
            b = case.primal(case.p0 - case.h, 50 + k, cfg.fd_spp)
            fds.append((a - b) / (2 * case.h))
        case.primal(case.p0, 0, cfg.spp)        # leave the scene at p0
        big_g, big_p = [], []
        if cfg.time_res:
            big = _Case(name, kind, cfg, tmpdir or tmp, res=cfg.time_res)
            for k in range(cfg.time_reps + 1):
                big_g.append(big.gradient(3000 + k, cfg.spp)[1])
                t0 = time.perf_counter()
                big.primal(big.p0, 3000 + k, cfg.spp)
                big_p.append(time.perf_counter() - t0)
    grads, fds = np.array(grads), np.array(fds)
    ad, ad_sd = float(grads.mean()), float(grads.std(ddof=1))
    ad_se = ad_sd / np.sqrt(len(grads))
    fd, fd_se = float(fds.mean()), float(fds.std(ddof=1) / np.sqrt(len(fds)))
    sigma = float(np.hypot(ad_se, fd_se))
    t_grad = float(np.median(tg[1:] if len(tg) > 1 else tg))
    t_primal = float(np.median(tp[1:] if len(tp) > 1 else tp))
    return {"scene": name, "integrator": kind, "param": SCENES[name][3], "p": case.p0,
            "h": case.h, "faces": case.faces, "spp": cfg.spp, "seeds": cfg.seeds,
            "fd_spp": cfg.fd_spp, "fd_seeds": cfg.fd_seeds,
            "ad": ad, "ad_se": float(ad_se), "ad_sd": ad_sd, "fd": fd, "fd_se": fd_se,
            "error": ad - fd, "sigma": sigma, "z": (ad - fd) / sigma if sigma > 0 else 0.0,
            "t_grad": t_grad, "t_primal": t_primal, "ratio": t_grad / t_primal,
            "time_res": cfg.time_res,
            "t_grad_big": float(np.median(big_g[1:])) if big_g else None,
            "t_primal_big": float(np.median(big_p[1:])) if big_p else None,
            "ratio_big": float(np.median(big_g[1:]) / np.median(big_p[1:])) if big_g else None,
            "finite": bool(np.all(np.isfinite(grads)) and np.all(np.isfinite(fds)))}


def targets(lg: dict, proj: dict) -> dict:
    """The three targets of one scene: lg_prb's |error| <= prb_projective's
    (or both within 2 sigma of their FDs), its per-estimate standard
    deviation <= 2x prb_projective's, its gradient pass <= 3x its primal
    (at the timing's size, ``time_res``, where there is one: the small
    image's passes are launch-bound)."""
    err_ok = (abs(lg["error"]) <= abs(proj["error"])
              or (abs(lg["z"]) <= 2 and abs(proj["z"]) <= 2))
    ratio = lg["ratio_big"] if lg.get("ratio_big") is not None else lg["ratio"]
    return {"error": bool(err_ok), "se": bool(lg["ad_sd"] <= 2 * proj["ad_sd"]),
            "time": bool(ratio <= 3)}


def run(log=None, quick=False, cfg: ProjectiveConfig | None = None) -> dict:
    """The section: every scene of ``cfg.scenes`` with both integrators."""
    import mitsuba as mi
    from .common import VARIANT
    if mi.variant() is None:
        mi.set_variant(VARIANT)
    import lgshape
    lgshape.register_plugins()
    log = log or (lambda msg: None)
    cfg = cfg or (QUICK if quick else FULL)
    records, verdicts = [], {}
    for name in cfg.scenes:
        pair = {}
        for kind in ("lg_prb", "prb_projective"):
            t0 = time.perf_counter()
            r = measure(name, kind, cfg)
            r["seconds"] = round(time.perf_counter() - t0, 1)
            records.append(r)
            pair[kind] = r
            log(f"projective {name} {kind}: AD {r['ad']:.4g} +- {r['ad_se']:.2g}, FD "
                f"{r['fd']:.4g} +- {r['fd_se']:.2g} (z {r['z']:.2f}); grad/primal "
                f"{r['ratio']:.2f} ({r['ratio_big'] or 0:.2f} at {cfg.time_res}^2) "
                f"in {r['seconds']} s")
        verdicts[name] = targets(pair["lg_prb"], pair["prb_projective"])
    return {"meta": {k: getattr(cfg, k) for k in ("res", "spp", "seeds", "fd_spp", "fd_seeds",
                                                  "grid", "time_res", "time_reps")}
            | {"scenes": list(cfg.scenes)},
            "records": records, "targets": verdicts}


def report(results) -> list:
    """The markdown lines of the section."""
    m = results["meta"]
    L = ["## Gradients against prb_projective\n",
         f"d mean(image) / d p of lg_prb on the implicit surface against Mitsuba's "
         f"prb_projective on a marching-cubes mesh of it ({m['grid']}^3 samples; the "
         f"parameter moves the vertices analytically), {m['res']} x {m['res']} pixels, "
         f"max_depth 3. AD: {m['seeds']} seeds at {m['spp']} spp (SE of the mean; sd: one "
         f"estimate's); FD: central differences of the same scene's primal, "
         f"{m['fd_seeds']} seeds at {m['fd_spp']} spp. z = (AD - FD) / combined SE. "
         f"Times: one gradient pass (render + backward) against one primal render at "
         f"{m['spp']} spp, medians after the first; at size: the same at "
         f"{m.get('time_res') or '-'}^2, {m.get('time_reps', 0)} repetitions.\n",
         "| scene | integrator | AD | SE | sd/estimate | FD | FD SE | AD - FD | z | "
         "grad s | primal s | grad/primal | at size: grad s | primal s | grad/primal |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]

    def fmt(v, spec):
        return "-" if v is None else format(v, spec)
    for r in results["records"]:
        L.append(f"| {r['scene']} | {r['integrator']} | {r['ad']:.4g} | {r['ad_se']:.2g} | "
                 f"{r['ad_sd']:.2g} | {r['fd']:.4g} | {r['fd_se']:.2g} | {r['error']:.2g} | "
                 f"{r['z']:.2f} | {r['t_grad']:.3g} | {r['t_primal']:.3g} | "
                 f"{r['ratio']:.2f} | {fmt(r.get('t_grad_big'), '.3g')} | "
                 f"{fmt(r.get('t_primal_big'), '.3g')} | {fmt(r.get('ratio_big'), '.2f')} |")
    L.append("")
    for name, t in results["targets"].items():
        L.append(f"- {name}: |error| <= prb_projective's (or both within 2 SE): "
                 f"{'met' if t['error'] else 'NOT met'}; sd <= 2x prb_projective's: "
                 f"{'met' if t['se'] else 'NOT met'}; gradient pass <= 3x primal: "
                 f"{'met' if t['time'] else 'NOT met'}")
    L.append("")
    return L
