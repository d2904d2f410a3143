"""The benchmark's speed section: lgshape against the alternatives, every
number measured in the same process and run.

**Rays per second**, for every library surface (:data:`lgshape.surfaces.LIBRARY`)
and three kinds of rays:

- ``camera``: the benchmark's primary rays (:func:`lgshape.camera.primary_rays`,
  ``res`` x ``res``);
- ``incoherent``: ``incoherent`` rays with uniform random origins in the box
  and uniform random directions (as after a diffuse bounce; fixed seed
  :data:`SEED`);
- ``shadow``: any-hit rays from the points lgshape's camera trace hit (its
  float64 t), moved :data:`SHADOW_OFFSET` box diagonals along the normal to
  the side the camera sees, towards a fixed point light outside the box
  (:func:`light_position`); ``t_max`` is the distance to the light.

Methods, each on the same prepared rays (:class:`lgshape.bench.common.Rays`) and
timed together by :func:`lgshape.bench.common.timed_together` (the median of timed
samples after a warm-up, each sample repeating the trace for at least
``min_sample`` s; the methods' samples interleaved round by round, and a
ratio the median of the rounds' paired ratios):

- ``lgshape``: ``lgshape.Surface(spec)`` at its default settings;
  ``.trace(o, d)`` for camera and incoherent rays, ``.occluded(o, d, t_max)``
  for shadow rays (evaluations and iterations per ray of the shadow rays come
  from one more, untimed ``.trace(..., any_hit=True)``);
- ``sphere_trace``: :func:`lgshape.bench.baselines.sphere_trace` with the
  valid global Lipschitz bound of interval arithmetic
  (:func:`lgshape.bench.common.global_L`) and eps = 1e-5 box diagonals (as
  :func:`lgshape.bench.baselines.sphere_runner`); for shadow rays its nearest
  hit before t_max (the search stops there);
- ``mesh``: the marching-cubes mesh of f / |grad f| sampled at ``mesh_res``^3
  vertices (:func:`lgshape.bench.baselines.sample_grid`, as
  :func:`lgshape.bench.baselines.mesh_runner`) traced by Mitsuba's Embree:
  ``scene.ray_intersect_preliminary`` for camera and incoherent rays,
  ``scene.ray_test`` for shadow rays.

Ratios are the other method's time over lgshape's (above 1: lgshape is
faster). The targets, printed beside them: at least :data:`TARGET_SPHERE`
times the sphere tracer on every surface but ``sphere`` (at least
:data:`TARGET_SPHERE_ON_SPHERE` there), at least :data:`TARGET_MESH` times the
mesh everywhere. ``agree`` is the fraction of rays on which a method's hit /
miss (occluded / not) answer is lgshape's (lgshape's answers are guaranteed;
the others' are not, and a shadow ray the sphere tracer stops at its start
point is a fast, wrong answer).

**Render level**: ``scenes/cornell.xml`` rendered by ``lg_path`` as it is,
against the same scene with the tangle replaced by its marching-cubes mesh
(``mesh_res``^3 samples, a PLY file in a temporary folder, same ``to_world``
and BSDF, faces wound so that the normals point towards f > 0 as lgsurface's
do) rendered by Mitsuba's ``path`` (same ``max_depth``, ``rr_depth``); the
median of ``render_repeats`` ``mi.render`` timings after one warm-up render.
Target: lg_path / path at most :data:`TARGET_CORNELL`.

**Gradient pass** (:func:`bench_gradients`): the same two scenes under
``lg_prb`` and Mitsuba's ``prb``: a primal render against a gradient pass
(``mi.render`` with parameters differentiable, ``dr.backward`` of the image
mean), interleaved; the walls' albedo in both, and the tangle's
``to_world`` too for lg_prb. Targets: lg_prb's gradient / primal ratio no
worse than prb's, and at most :data:`TARGET_GRADIENT`.

**Host time per render** (:func:`bench_host`): the emitter scene at 64 x 64,
64 spp under lg_path (frozen renders, and every render traced) against
Mitsuba's ``path`` with the native sphere, interleaved; each render's
kernel time from Dr.Jit's kernel history, the rest the host's. Target:
lg_path / path at most :data:`TARGET_HOST`.

**First-image latency**: the default scene (``make render``'s,
``scenes/cornell.xml``) in a subprocess (:mod:`lgshape.bench.probe`) with
``HOME`` set to a fresh
temporary folder (Dr.Jit keeps its kernel cache in ``$HOME/.drjit``): the
first ``mi.render`` at ``probe_spp`` spp minus a second identical one in the
same process is the kernel compile time with an empty cache; a second
subprocess with the same ``HOME`` repeats it with the cache filled (the
cached kernels are reused across runs).

:func:`run` returns a JSON-ready dict, :func:`chart` draws the ratios,
:func:`report` writes the markdown section. Standalone:
``python -m lgshape.bench.speed --out DIR [--quick] [--surfaces ...]``.
Dr.Jit, Mitsuba, scikit-image and matplotlib are imported where they are used.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from dataclasses import asdict, dataclass

import numpy as np

import lgshape

from ..camera import primary_rays
from ..expr import evaluate, gradient
from ..surfaces import LIBRARY
from .baselines import frozen, sample_grid, sphere_trace
from .common import VARIANT, Rays, Runner, finite, git_commit, global_L, machine, mitsuba_mesh, \
    paired_ratio, plain_surface, stderr_log, timed_together

SEED = 52
KINDS = ("camera", "incoherent", "shadow")
METHODS = ("lgshape", "sphere_trace", "mesh")

#: The targets: time ratios (other / lgshape) at least these.
TARGET_SPHERE, TARGET_SPHERE_ON_SPHERE, TARGET_MESH = 2.0, 1.0, 1.0
#: lg_path's render time over path's on the mesh, at most this.
TARGET_CORNELL = 1.5
#: lg_path's time a small render (mostly the host's) over path's, at most this.
TARGET_HOST = 2.0

#: Shadow-ray origins: this many box diagonals off the surface along the normal.
SHADOW_OFFSET = 1e-3
#: The point light: this many half box diagonals from the centre, this way.
LIGHT_DISTANCE, LIGHT_DIR = 2.5, (-0.35, 0.25, 0.9)
#: The sphere tracer's threshold, in box diagonals.
ST_EPS = 1e-5
#: Rows where the sphere tracer agrees with lgshape on fewer rays are noted.
AGREE_NOTE = 0.99

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
CORNELL = os.path.join(ROOT, "scenes", "cornell.xml")
PROBE_TIMEOUT = 900
#: The first-image probes, in order, sharing one fresh HOME: an empty kernel
#: cache, then twice the cache the earlier ones filled.
PROBES = ("cold", "warm", "warm_again")


@dataclass(frozen=True)
class SpeedConfig:
    surfaces: tuple
    res: int                 # camera rays res x res (shadow rays from their hits)
    incoherent: int          # incoherent rays
    mesh_res: int            # marching-cubes samples per axis (rays and cornell)
    repeats: int             # timed samples after the warm-up
    min_sample: float        # seconds per timing sample
    render_res: int          # cornell film, render_res x render_res
    render_spp: int
    render_repeats: int
    probe_res: int           # first-image latency: film and spp
    probe_spp: int
    gradient_rounds: int = 3  # interleaved rounds of the gradient timings


FULL = SpeedConfig(surfaces=tuple(LIBRARY), res=512, incoherent=262144, mesh_res=256,
                   repeats=5, min_sample=0.1, render_res=256, render_spp=16, render_repeats=3,
                   probe_res=256, probe_spp=1, gradient_rounds=7)
QUICK = SpeedConfig(surfaces=("sphere", "torus", "tangle"), res=64, incoherent=4096,
                    mesh_res=64, repeats=3, min_sample=0.01, render_res=32, render_spp=4,
                    render_repeats=3, probe_res=16, probe_spp=1)


# ---- Rays ---------------------------------------------------------------------

def incoherent_rays(spec, n: int, seed: int = SEED):
    """n rays, origins uniform in the box, directions uniform on the sphere
    (float32 (n, 3) arrays)."""
    rng = np.random.default_rng(seed)
    lo, hi = (np.asarray(v, np.float64) for v in spec.bbox)
    o = lo + (hi - lo) * rng.random((n, 3))
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return o.astype(np.float32), d.astype(np.float32)


def light_position(spec):
    """The fixed point light, outside the box (float64 (3,))."""
    lo, hi = (np.asarray(v, np.float64) for v in spec.bbox)
    u = np.asarray(LIGHT_DIR, np.float64)
    return 0.5 * (lo + hi) + LIGHT_DISTANCE * 0.5 * np.linalg.norm(hi - lo) * u / np.linalg.norm(u)


def shadow_rays(spec, surf, o, d, t, hit, offset: float = SHADOW_OFFSET, light=None):
    """Shadow rays from the hit points o + t d (float64 t) of the rays that
    hit: origins ``offset`` box diagonals along the unit normal of ``surf``,
    turned to the side the ray came from, towards ``light`` (default
    :func:`light_position`). Returns float32 (origins, unit directions,
    t_max = distance to the light) and the indices of the rays used."""
    idx = np.flatnonzero(np.asarray(hit, bool) & np.isfinite(t))
    o64, d64 = o[idx].astype(np.float64), d[idx].astype(np.float64)
    p = o64 + np.asarray(t, np.float64)[idx, None] * d64
    if len(idx):
        n = np.asarray(surf.normal(p.astype(np.float32)), np.float64).reshape(3, -1).T
    else:
        n = np.zeros((0, 3))
    n = np.where(np.sum(n * d64, axis=1, keepdims=True) > 0, -n, n)
    diag = float(np.linalg.norm(np.subtract(spec.bbox[1], spec.bbox[0])))
    start = p + offset * diag * n
    light = light_position(spec) if light is None else np.asarray(light, np.float64)
    v = light - start
    dist = np.linalg.norm(v, axis=1)
    return (start.astype(np.float32), (v / dist[:, None]).astype(np.float32),
            dist.astype(np.float32), idx)


class ShadowRays:
    """Shadow rays in the forms the methods take: :class:`lgshape.bench.common.Rays`
    plus ``t_max`` (Dr.Jit Float) and Mitsuba's ray with ``maxt`` = t_max."""

    def __init__(self, o, d, t_max):
        import drjit as dr
        import mitsuba as mi
        self.rays = Rays(o, d)
        self.t_max = np.asarray(t_max, np.float32)
        self.t_max_dr = mi.Float(self.t_max)
        self.rays.ray.maxt = mi.Float(self.t_max)
        dr.eval(self.t_max_dr, self.rays.ray)

    def __len__(self):
        return len(self.t_max)


# ---- Methods ------------------------------------------------------------------

_KEYS = ("hit", "t", "evals", "iterations", "capped")


def _read(out):
    """Runner output -> numpy fields: (hit, t, evals, iterations, capped), or
    (t,) alone (Mitsuba's preliminary intersection: hit where t is finite)."""
    if len(out) == 1 and out[0] is not None and not _is_bool(out[0]):
        t = np.asarray(out[0]).astype(np.float64)
        return {"hit": np.isfinite(t), "t": t}
    return {k: np.asarray(v) for k, v in zip(_KEYS, out)}


def _is_bool(v):
    import drjit as dr
    return dr.is_mask_v(v)


def _runner(method, setting, run, build_s=0.0, extra=None):
    return Runner(method, setting, run, _read, lambda t: None, 0, build_s, extra or {})


@dataclass
class Method:
    """One method on one ray set: the timed runner and, for shadow rays, an
    untimed call with the per-ray statistics (None: the timed output has them)."""
    runner: object
    stats: object = None


def lgshape_method(surf, rays, shadow: ShadowRays | None = None, build_s=0.0) -> Method:
    if shadow is None:
        def run():
            r = surf.trace(rays.o_dr, rays.d_dr)
            return r.hit, r.t, r.evals, r.iterations, r.capped
        return Method(_runner("lgshape", "Surface(spec): .trace", run, build_s))
    s = shadow.rays

    def run_shadow():
        return (surf.occluded(s.o_dr, s.d_dr, shadow.t_max_dr),)

    def stats():
        r = surf.trace(s.o_dr, s.d_dr, t_max=shadow.t_max_dr, any_hit=True)
        return r.hit, r.t, r.evals, r.iterations, r.capped
    return Method(_runner("lgshape", "Surface(spec): .occluded", run_shadow, build_s), stats)


def sphere_method(surf_plain, L, rays, shadow: ShadowRays | None = None) -> Method:
    """Plain sphere tracing with the global L (``surf_plain``: the baselines'
    view of f, see :func:`lgshape.bench.common.plain_surface`)."""
    eps = ST_EPS * surf_plain.diagonal
    setting = f"global L {L:.4g}, eps {ST_EPS:g} diag"
    extra = {"lipschitz_L": L}
    st = frozen(sphere_trace, surf_plain, L=L, relax=1.0, eps=eps)
    if shadow is None:
        def run():
            r = st(rays.o_dr, rays.d_dr)
            return r.hit, r.t, r.evals, r.iterations, r.capped
        return Method(_runner("sphere_trace", setting, run, extra=extra))
    s = shadow.rays

    def trace():
        return st(s.o_dr, s.d_dr, shadow.t_max_dr)

    def stats():
        r = trace()
        return r.hit, r.t, r.evals, r.iterations, r.capped
    return Method(_runner("sphere_trace", setting + ", a hit before t_max",
                          lambda: (trace().hit,), extra=extra), stats)


def mesh_method(scene, rays, shadow: ShadowRays | None, setting, build_s, extra) -> Method:
    if shadow is None:
        return Method(_runner("mesh", setting + ": ray_intersect_preliminary",
                              lambda: (scene.ray_intersect_preliminary(rays.ray).t,),
                              build_s, extra))
    ray = shadow.rays.ray
    return Method(_runner("mesh", setting + ": ray_test", lambda: (scene.ray_test(ray),),
                          build_s, extra))


def marching_mesh(spec, f):
    """Marching cubes of the samples ``f`` ([z, y, x], spanning the box, as
    :func:`lgshape.bench.baselines.sample_grid`), in the surface's coordinates: (vertices
    float64 (V, 3), faces int (F, 3)), wound so that the face normals point
    towards f > 0 (the side lgsurface's normal points to), or None where the
    samples have no sign change."""
    from skimage.measure import marching_cubes
    lo, hi = (np.asarray(v, np.float64) for v in spec.bbox)
    res = f.shape[0]
    try:
        v, faces, _, _ = marching_cubes(f, 0.0, spacing=tuple((hi - lo)[::-1] / (res - 1)))
    except (ValueError, RuntimeError):
        return None
    v = v[:, ::-1] + lo                                   # [z, y, x] -> (x, y, z)
    # Winding: the face normals against grad f at the face centres (a sample).
    k = np.linspace(0, len(faces) - 1, min(len(faces), 4096)).astype(int)
    tri = v[faces[k]]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    c = tri.mean(axis=1)
    with np.errstate(all="ignore"):
        g = evaluate(list(gradient(spec.expr)), {"x": c[:, 0], "y": c[:, 1], "z": c[:, 2]})
    g = np.stack([np.broadcast_to(gi, len(c)) for gi in g], 1)
    if np.sum(np.sign(np.nan_to_num(np.sum(fn * g, axis=1)))) < 0:
        faces = faces[:, [0, 2, 1]]
    return v, faces


def _mean(v):
    return None if v is None or len(v) == 0 else float(np.mean(v))


def measure(methods: dict, n, cfg: SpeedConfig) -> dict:
    """The records of the methods on one ray set ({key: Method}, the first
    lgshape), timed together (:func:`lgshape.bench.common.timed_together`: their
    samples interleaved round by round), with their hit answers' agreement
    with the first's."""
    timed = timed_together({k: m.runner for k, m in methods.items()}, cfg.repeats,
                           cfg.min_sample)
    recs, ref_hit = {}, None
    for key, method in methods.items():
        res, seconds, samples = timed[key]
        if method.stats is not None:
            stats = _read(method.stats())
            res = {**stats, "hit": res["hit"]}
        hit = res["hit"].astype(bool)
        rec = {"setting": method.runner.setting, **method.runner.extra, "seconds": seconds,
               "samples": samples, "mrays_per_s": n / seconds / 1e6,
               "hit_fraction": float(np.mean(hit)),
               "evals_per_ray": _mean(res.get("evals")),
               "iterations_per_ray": _mean(res.get("iterations")),
               "capped": None if res.get("capped") is None else int(np.sum(res["capped"]))}
        if method.runner.build_s:
            rec["build_s"] = method.runner.build_s
        if ref_hit is None:
            ref_hit = hit
        else:
            rec["agree"] = float(np.mean(hit == ref_hit))
        recs[key] = rec
    return recs


def sphere_target(surface: str) -> float:
    return TARGET_SPHERE_ON_SPHERE if surface == "sphere" else TARGET_SPHERE


def _ratio(other, lg):
    """The other method's time over lgshape's: the median of the rounds'
    paired ratios (both timed in the same rounds); for records without
    samples (an older run's JSON, reported again), the quotient of their
    median times."""
    if not other or not lg or not other.get("seconds") or not lg.get("seconds"):
        return None
    if other.get("samples") and lg.get("samples"):
        return paired_ratio(other["samples"], lg["samples"])
    return other["seconds"] / lg["seconds"]


def bench_surface(name, cfg: SpeedConfig, log, keep_mesh=False):
    """The rows of one surface (one per ray kind), and its mesh (vertices,
    faces) when ``keep_mesh``."""
    import mitsuba as mi
    spec = LIBRARY[name]()
    t0 = time.perf_counter()
    surf = lgshape.Surface(spec)
    lg_build = time.perf_counter() - t0
    plain = plain_surface(spec)
    L = global_L(spec)
    t0 = time.perf_counter()
    mesh = marching_mesh(spec, sample_grid(spec, cfg.mesh_res))
    scene = None if mesh is None else mi.load_dict({"type": "scene",
                                                    "shape": mitsuba_mesh(*mesh)})
    mesh_build = time.perf_counter() - t0
    mesh_extra = {"triangles": 0 if mesh is None else int(len(mesh[1]))}
    mesh_setting = f"{cfg.mesh_res}^3 marching cubes, {_mesh_tracer(mi.variant())}"
    log(f"speed {name}: lgshape build {lg_build:.2f} s, global L {L:.4g}, mesh "
        f"{mesh_extra['triangles']} triangles in {mesh_build:.1f} s")

    o_cam, d_cam = primary_rays(spec.bbox, cfg.res)
    rows = []
    for kind in KINDS:
        shadow = None
        if kind == "camera":
            rays = cam_rays = Rays(o_cam, d_cam)
        elif kind == "incoherent":
            rays = Rays(*incoherent_rays(spec, cfg.incoherent))
        else:
            r = surf.trace(cam_rays.o_dr, cam_rays.d_dr)
            so, sd, st, _ = shadow_rays(spec, surf, o_cam, d_cam,
                                        np.asarray(r.t64, np.float64), np.asarray(r.hit))
            shadow = ShadowRays(so, sd, st)
            rays = shadow.rays
        n = len(rays.o)
        row = {"surface": name, "kind": kind, "rays": n}
        methods = {"lgshape": lgshape_method(surf, rays, shadow, lg_build),
                   "sphere_trace": sphere_method(plain, L, rays, shadow),
                   "mesh": None if scene is None else mesh_method(
                       scene, rays, shadow, mesh_setting, mesh_build, mesh_extra)}
        present = {k: m for k, m in methods.items() if m is not None and n > 0}
        row.update({k: None for k in methods})
        if present:
            row.update(measure(present, n, cfg))
        row["ratio_sphere"] = _ratio(row["sphere_trace"], row["lgshape"])
        row["ratio_mesh"] = _ratio(row["mesh"], row["lgshape"])
        row["target_sphere"], row["target_mesh"] = sphere_target(name), TARGET_MESH
        row["met_sphere"] = None if row["ratio_sphere"] is None else \
            bool(row["ratio_sphere"] >= row["target_sphere"])
        row["met_mesh"] = None if row["ratio_mesh"] is None else \
            bool(row["ratio_mesh"] >= row["target_mesh"])
        rows.append(row)
        log(f"  {kind:10} {n:7d} rays: lgshape {_mr(row['lgshape'])} Mrays/s, sphere "
            f"{_mr(row['sphere_trace'])} (x{_x(row['ratio_sphere'])}), mesh "
            f"{_mr(row['mesh'])} (x{_x(row['ratio_mesh'])})")
    return rows, (mesh if keep_mesh else None)


def _mr(rec):
    return "–" if not rec or rec.get("mrays_per_s") is None else f"{rec['mrays_per_s']:.2f}"


def _x(v):
    return "–" if v is None else f"{v:.2f}"


# ---- Render level ---------------------------------------------------------------

def mesh_scene_xml(scene_path, ply_for):
    """The scene's XML with every ``lgsurface`` of a library surface (default
    parameters) replaced by a ``ply`` shape (``ply_for(surface name)`` -> file
    path) with the same children otherwise (to_world, BSDF), and ``lg_path``
    by ``path`` (same properties). Returns (text, names replaced)."""
    tree = ET.parse(scene_path)
    root = tree.getroot()
    names = []
    for integ in root.iter("integrator"):
        if integ.get("type") == "lg_path":
            integ.set("type", "path")
    for shape in root.iter("shape"):
        if shape.get("type") != "lgsurface":
            continue
        own = [c for c in shape if c.get("name") not in (None, "to_world")
               and c.tag not in ("bsdf", "ref", "transform")]
        if [(c.tag, c.get("name")) for c in own] != [("string", "surface")]:
            raise ValueError(f"{scene_path}: only lgsurfaces given by a library 'surface' "
                             f"(default parameters) can be replaced by a mesh")
        name = own[0].get("value")
        shape.remove(own[0])
        shape.set("type", "ply")
        ET.SubElement(shape, "string", {"name": "filename", "value": ply_for(name)})
        names.append(name)
    return ET.tostring(root, encoding="unicode"), names


def time_renders(scene, spp, repeats):
    """(first render s, median of ``repeats`` renders after it, mean of the image)."""
    import drjit as dr
    import mitsuba as mi

    def once():
        t0 = time.perf_counter()
        img = mi.render(scene, spp=spp, seed=0)
        dr.eval(img)
        dr.sync_thread()
        return time.perf_counter() - t0, img
    first, img = once()
    samples = [once()[0] for _ in range(repeats)]
    return first, float(np.median(samples)), samples, float(np.mean(np.asarray(img)[..., :3]))


def bench_cornell(cfg: SpeedConfig, log, meshes=None):
    """lg_path on cornell.xml against path on its mesh version."""
    import mitsuba as mi
    meshes = dict(meshes or {})
    defines = {"spp": str(cfg.render_spp), "resx": str(cfg.render_res),
               "resy": str(cfg.render_res)}
    rec = {"scene": os.path.relpath(CORNELL, ROOT),
           "res": cfg.render_res, "spp": cfg.render_spp, "repeats": cfg.render_repeats,
           "mesh_res": cfg.mesh_res}
    with tempfile.TemporaryDirectory(prefix="lgshape-speed-") as tmp:
        triangles = {}

        def ply_for(name):
            if name not in meshes:
                spec = LIBRARY[name]()
                meshes[name] = marching_mesh(spec, sample_grid(spec, cfg.mesh_res))
            v, faces = meshes[name]
            path = os.path.join(tmp, f"{name}.ply")
            mitsuba_mesh(v, faces, name).write_ply(path)
            triangles[name] = int(len(faces))
            return path
        text, names = mesh_scene_xml(CORNELL, ply_for)
        lg_scene = mi.load_file(CORNELL, **defines)
        mesh_scene = mi.load_string(text, **defines)
        rec["meshed"] = names
        rec["triangles"] = triangles
        for key, scene in (("lg_path", lg_scene), ("path", mesh_scene)):
            first, med, samples, mean = time_renders(scene, cfg.render_spp, cfg.render_repeats)
            rec[key] = {"first_s": first, "seconds": med, "samples_s": samples,
                        "image_mean": mean}
            log(f"cornell {key}: first render {first:.2f} s, then {med:.3f} s "
                f"(median of {cfg.render_repeats}), image mean {mean:.4f}")
    rec["ratio"] = rec["lg_path"]["seconds"] / rec["path"]["seconds"]
    rec["target"] = TARGET_CORNELL
    rec["met"] = rec["ratio"] <= TARGET_CORNELL
    return rec


#: lg_prb's gradient pass on cornell.xml: at most this many times its primal.
TARGET_GRADIENT = 3.0


def _integrator_xml(text, kind, **booleans):
    """The scene text with its integrator's type set to ``kind`` (and the
    boolean properties ``booleans`` added)."""
    root = ET.fromstring(text)
    for integ in root.iter("integrator"):
        integ.set("type", kind)
        for name, value in booleans.items():
            ET.SubElement(integ, "boolean", name=name, value=str(bool(value)).lower())
    return ET.tostring(root, encoding="unicode")


def time_gradients(cases, spp, repeats):
    """Primal renders and gradient passes (mi.render with the parameters
    differentiable, dr.backward of the image's mean) of each case (name ->
    (scene, keys)), interleaved round by round after a warm-up of each: in
    every round each case runs both, the cases and the two kinds in an
    order that turns from round to round, so that the machine's drift (other
    jobs, clocks) falls on all alike. Per case: {"primal_s", "gradient_s"
    (medians), "samples", "ratio" (the median of the rounds' ratios),
    "ratios", "grad_norm"}."""
    import drjit as dr
    import mitsuba as mi

    def runner(scene, keys):
        params = mi.traverse(scene)

        def primal():
            img = mi.render(scene, spp=spp, seed=0)
            dr.eval(img)
            dr.sync_thread()

        def gradient():
            for k in keys:
                dr.enable_grad(params[k])
            params.update()
            img = mi.render(scene, params, spp=spp, seed=0, seed_grad=1)
            dr.backward(dr.mean(img, axis=None))
            grads = [dr.grad(params[k]) for k in keys]
            grads = [g.matrix if isinstance(g, mi.AffineTransform4f) else g for g in grads]
            dr.eval(grads)
            dr.sync_thread()
            norm = float(sum(float(np.sum(np.square(np.asarray(g, np.float64))))
                             for g in grads)) ** 0.5
            for k in keys:
                dr.disable_grad(params[k])
            params.update()
            return norm
        return {"primal": primal, "gradient": gradient}

    runs = {name: runner(scene, keys) for name, (scene, keys) in cases.items()}
    norms = {}
    for name, run in runs.items():
        run["primal"]()
        norms[name] = run["gradient"]()
    rounds = {name: {"primal": [], "gradient": []} for name in runs}
    names = list(runs)
    for r in range(repeats):
        for name in names[r % len(names):] + names[:r % len(names)]:
            for which in (("primal", "gradient") if r % 2 == 0 else ("gradient", "primal")):
                t0 = time.perf_counter()
                runs[name][which]()
                rounds[name][which].append(time.perf_counter() - t0)
    out = {}
    for name, times in rounds.items():
        ratios = [g / p for g, p in zip(times["gradient"], times["primal"])]
        out[name] = {"primal_s": float(np.median(times["primal"])),
                     "gradient_s": float(np.median(times["gradient"])),
                     "samples": times, "ratios": ratios, "ratio": float(np.median(ratios)),
                     "grad_norm": norms[name]}
    return out


def bench_gradients(cfg: SpeedConfig, log, meshes=None):
    """Inverse rendering's cost on cornell.xml: lg_prb's gradient pass
    against its primal, beside Mitsuba's prb on the same scene with the
    tangle as a marching-cubes mesh (its gradient / primal ratio is the
    anchor). The parameters: the walls' albedo (both scenes) and, for
    lg_prb, the tangle's to_world too."""
    import mitsuba as mi
    meshes = dict(meshes or {})
    defines = {"spp": str(cfg.render_spp), "resx": str(cfg.render_res),
               "resy": str(cfg.render_res)}
    rec = {"scene": os.path.relpath(CORNELL, ROOT), "res": cfg.render_res,
           "spp": cfg.render_spp, "mesh_res": cfg.mesh_res}
    with tempfile.TemporaryDirectory(prefix="lgshape-grad-") as tmp:
        def ply_for(name):
            if name not in meshes:
                spec = LIBRARY[name]()
                meshes[name] = marching_mesh(spec, sample_grid(spec, cfg.mesh_res))
            v, faces = meshes[name]
            path = os.path.join(tmp, f"{name}.ply")
            mitsuba_mesh(v, faces, name).write_ply(path)
            return path
        with open(CORNELL) as fh:
            text = fh.read()
            lg_text = _integrator_xml(text, "lg_prb")
            no_edges_text = _integrator_xml(text, "lg_prb", shadow_edges=False)
        mesh_text, _ = mesh_scene_xml(CORNELL, ply_for)
        mesh_text = _integrator_xml(mesh_text, "prb")
        cases = {"lg_prb": (mi.load_string(lg_text, **defines), ["white.reflectance.value"]),
                 "prb": (mi.load_string(mesh_text, **defines), ["white.reflectance.value"]),
                 "lg_prb_shape": (mi.load_string(lg_text, **defines),
                                  ["white.reflectance.value", "tangle.to_world"]),
                 "lg_prb_shape_no_shadow_edges": (
                     mi.load_string(no_edges_text, **defines),
                     ["white.reflectance.value", "tangle.to_world"])}
        rec["repeats"] = cfg.gradient_rounds
        timed = time_gradients(cases, cfg.render_spp, rec["repeats"])
        for key, (_, keys) in cases.items():
            r = timed[key]
            r["parameters"] = keys
            rec[key] = r
            log(f"gradients {key}: primal {r['primal_s']:.3f} s, gradient pass "
                f"{r['gradient_s']:.3f} s (x{r['ratio']:.2f}, rounds "
                f"{min(r['ratios']):.2f}-{max(r['ratios']):.2f}; parameters {', '.join(keys)})")
    rec["target_ratio"] = TARGET_GRADIENT
    rec["met_ratio"] = rec["lg_prb"]["ratio"] <= TARGET_GRADIENT
    rec["met_anchor"] = rec["lg_prb"]["ratio"] <= rec["prb"]["ratio"]
    rec["met_ratio_shape"] = rec["lg_prb_shape"]["ratio"] <= TARGET_GRADIENT
    return rec


def emitter_scene(lamp, integrator, res=32, spp=64, radiance=None, **integrator_props):
    """A lamp (a shape with an area emitter of radiance ``radiance``, a
    texture's dict, default a uniform 4; e.g. a sphere of radius 0.3 at
    (0, 0.4, 0)) above a diffuse floor, seen from the front: the emitter's
    own sampling decides most of the noise (also the scene of
    tests/test_48_emitters.py)."""
    radiance = radiance or {"type": "rgb", "value": 4.0}
    import mitsuba as mi
    return mi.load_dict({
        "type": "scene", "integrator": {"type": integrator, **integrator_props},
        "sensor": {"type": "perspective", "fov": 45,
                   "to_world": mi.ScalarTransform4f().look_at([0, 0.5, 3], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": res, "height": res,
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "floor": {"type": "rectangle",
                  "to_world": mi.ScalarTransform4f().translate([0, -0.3, 0])
                  @ mi.ScalarTransform4f().rotate([1, 0, 0], -90) @ mi.ScalarTransform4f().scale(2),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.6}}},
        "lamp": {**lamp, "emitter": {"type": "area", "radiance": radiance}}})


def bench_emitters(cfg: SpeedConfig, log, seeds=4):
    """An emitting lgsurface sphere under lg_path against Mitsuba's path with
    the native emitting sphere (its visible-cap sampling, the harder anchor)
    and with the sphere as a marching-cubes mesh (area sampling): the image
    MSE against a reference (path, native sphere, 64x the spp) at equal spp,
    and the render times; the MSE ratios against the native one."""
    import mitsuba as mi
    res, spp = max(32, cfg.render_res // 4), cfg.render_spp * 4
    spec = LIBRARY["sphere"](0.3)
    with tempfile.TemporaryDirectory(prefix="lgshape-emit-") as tmp:
        v, faces = marching_mesh(spec, sample_grid(spec, cfg.mesh_res))
        ply = os.path.join(tmp, "sphere.ply")
        mitsuba_mesh(v, faces, "sphere").write_ply(ply)
        move = mi.ScalarTransform4f().translate([0, 0.4, 0])
        lamps = {
            "lg_path, lgsurface": ({"type": "lgsurface", "surface": "sphere", "radius": 0.3,
                                    "to_world": move}, "lg_path"),
            "path, native sphere": ({"type": "sphere", "radius": 0.3, "center": [0, 0.4, 0]},
                                    "path"),
            "path, mesh": ({"type": "ply", "filename": ply, "to_world": move}, "path"),
        }
        rec = {"res": res, "spp": spp, "reference_spp": spp * 64, "seeds": seeds,
               "mesh_triangles": int(len(faces))}

        def measure(lamps, radiance=None):
            ref_scene = emitter_scene(lamps["path, native sphere"][0], "path", res, spp * 64,
                                      radiance=radiance, max_depth=3)
            ref = np.asarray(mi.render(ref_scene, seed=999), np.float64)
            methods = {}
            for key, (lamp, integrator) in lamps.items():
                scene = emitter_scene(lamp, integrator, res, spp, radiance=radiance,
                                      max_depth=3)
                mi.render(scene, seed=0)                       # compiles
                mse, secs = [], []
                for k in range(seeds):
                    t0 = time.perf_counter()
                    img = np.asarray(mi.render(scene, seed=k + 1), np.float64)
                    secs.append(time.perf_counter() - t0)
                    mse.append(float(np.mean((img - ref) ** 2)))
                methods[key] = {"mse": float(np.mean(mse)), "seconds": float(np.median(secs))}
                log(f"emitter {key}{', textured' if radiance else ''}: MSE {np.mean(mse):.3e} "
                    f"at {spp} spp, {np.median(secs):.3f} s")
            native = methods["path, native sphere"]
            for m in methods.values():
                m["mse_ratio"] = m["mse"] / native["mse"]
                # at equal time: MSE scales as 1 / spp, spp as 1 / time per sample
                m["mse_ratio_equal_time"] = m["mse_ratio"] * m["seconds"] / native["seconds"]
            return methods

        rec["methods"] = measure(lamps)
        # a textured radiance, the lgsurface against the native sphere (the
        # same uv convention)
        rec["textured"] = measure({k: lamps[k] for k in ("lg_path, lgsurface",
                                                         "path, native sphere")},
                                  textured_radiance())
    return rec


def bench_host(cfg: SpeedConfig, log, rounds=9):
    """Time per render at a size where the host's work (tracing the
    integrator's Python, launching kernels) is most of it: the emitter scene
    (:func:`emitter_scene`) at 64 x 64, 64 spp, under lg_path with the
    lamp an lgsurface, as it renders (frozen renders, :mod:`lgshape.plugins.frozen`)
    and with every render traced (``LGSHAPE_NO_FREEZE=1``), against Mitsuba's
    ``path`` with the native emitting sphere. Each method renders three times
    to warm up (trace, record), then the methods take turns for ``rounds``
    rounds (a new seed each render). Per method: the median seconds a
    render, the median of its kernels' execution time (Dr.Jit's kernel
    history) and the difference, the host's share; the count of kernels
    compiled after the warm-up (0 expected)."""
    import drjit as dr
    import mitsuba as mi
    res, spp = 64, 64
    lamp = {"type": "lgsurface", "surface": "sphere", "radius": 0.3,
            "to_world": mi.ScalarTransform4f().translate([0, 0.4, 0])}
    native = {"type": "sphere", "radius": 0.3, "center": [0, 0.4, 0]}
    methods = {"lg_path": (lamp, "lg_path", False), "lg_path, traced": (lamp, "lg_path", True),
               "path, native sphere": (native, "path", False)}
    scenes = {k: emitter_scene(l, i, res, spp, max_depth=3) for k, (l, i, _) in methods.items()}
    flag = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    saved = os.environ.get("LGSHAPE_NO_FREEZE")
    samples = {k: {"total": [], "kernels": [], "compiled": 0, "mean": []} for k in methods}
    seed = 0

    def once(key, timed):
        nonlocal seed
        seed += 1
        os.environ["LGSHAPE_NO_FREEZE"] = "1" if methods[key][2] else "0"
        dr.kernel_history()
        t0 = time.perf_counter()
        img = mi.render(scenes[key], seed=seed)
        dr.eval(img)
        dr.sync_thread()
        t = time.perf_counter() - t0
        hist = [h for h in dr.kernel_history() if h["type"] == dr.KernelType.JIT]
        if timed:
            rec = samples[key]
            rec["total"].append(t)
            rec["kernels"].append(sum(h["execution_time"] for h in hist) / 1e3)
            rec["compiled"] += sum(1 for h in hist if not h["cache_hit"])
            rec["mean"].append(float(np.mean(np.asarray(img)[..., :3])))

    try:
        for key in methods:
            for _ in range(3):
                once(key, False)
        keys = list(methods)
        for r in range(rounds):
            for j in range(len(keys)):
                once(keys[(j + r) % len(keys)], True)
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, flag)
        if saved is None:
            os.environ.pop("LGSHAPE_NO_FREEZE", None)
        else:
            os.environ["LGSHAPE_NO_FREEZE"] = saved
    out = {"res": res, "spp": spp, "rounds": rounds, "methods": {}}
    for key, rec in samples.items():
        total, kern = float(np.median(rec["total"])), float(np.median(rec["kernels"]))
        out["methods"][key] = {"seconds": total, "kernel_s": kern, "host_s": total - kern,
                               "compiled_after_warmup": rec["compiled"],
                               "image_mean": float(np.mean(rec["mean"])), "samples": rec["total"]}
        log(f"host time {key}: {total * 1e3:.1f} ms a render, kernels {kern * 1e3:.1f} ms, "
            f"{rec['compiled']} kernels compiled after the warm-up")
    base = out["methods"]["path, native sphere"]
    for key, m in out["methods"].items():
        m["ratio"] = paired_ratio(m["samples"], base["samples"])
    out["met"] = out["methods"]["lg_path"]["ratio"] <= TARGET_HOST
    return out


def textured_radiance():
    """The textured radiance of the emitter benchmark: a checkerboard of
    radiance 0.5 and 6 on a 12 x 6 grid of the surface's uv."""
    import mitsuba as mi
    return {"type": "checkerboard", "color0": 0.5, "color1": 6.0,
            "to_uv": mi.ScalarTransform4f().scale([12, 6, 1])}


def fog():
    """The homogeneous scattering medium of the media scenes."""
    return {"type": "homogeneous", "sigma_t": 2.0,
            "albedo": {"type": "rgb", "value": [0.8, 0.6, 0.3]}}


def media_scene(shapes, integrator, res=24, spp=64):
    """``shapes`` (id -> shape dict: e.g. a sphere of radius 0.6 holding a
    medium behind a null boundary) over a floor, lit by a point light and a
    sky (also the scene of tests/test_49_volpath.py)."""
    import mitsuba as mi
    return mi.load_dict({
        "type": "scene", "integrator": {"type": integrator, "max_depth": 16},
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at([0, 0.3, 3], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": res, "height": res,
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 0.3}},
        "lamp": {"type": "point", "position": [1.5, 2, 1.5],
                 "intensity": {"type": "rgb", "value": 10.0}},
        "floor": {"type": "rectangle",
                  "to_world": mi.ScalarTransform4f().translate([0, -0.7, 0])
                  @ mi.ScalarTransform4f().rotate([1, 0, 0], -90) @ mi.ScalarTransform4f().scale(3),
                  "bsdf": {"type": "diffuse"}},
        **shapes})


def bench_media(cfg: SpeedConfig, log):
    """A medium bounded by an implicit sphere under lg_volpath against the
    same scene under Mitsuba's volpath with the sphere native and as a
    marching-cubes mesh: render times (median of ``render_repeats`` after a
    warm-up) and the ratios against the mesh."""
    res, spp = cfg.render_res // 2, cfg.render_spp
    spec = LIBRARY["sphere"](0.6)
    with tempfile.TemporaryDirectory(prefix="lgshape-media-") as tmp:
        v, faces = marching_mesh(spec, sample_grid(spec, cfg.mesh_res))
        ply = os.path.join(tmp, "sphere.ply")
        mitsuba_mesh(v, faces, "sphere").write_ply(ply)
        cases = {"lg_volpath, lgsurface": ({"type": "lgsurface", "surface": "sphere",
                                            "radius": 0.6}, "lg_volpath"),
                 "volpath, native sphere": ({"type": "sphere", "radius": 0.6}, "volpath"),
                 "volpath, mesh": ({"type": "ply", "filename": ply}, "volpath")}
        rec = {"res": res, "spp": spp, "repeats": cfg.render_repeats,
               "mesh_triangles": int(len(faces)), "methods": {}}
        for key, (ball, integrator) in cases.items():
            shapes = {"ball": {**ball, "bsdf": {"type": "null"}, "interior": fog()}}
            first, med, samples, mean = time_renders(media_scene(shapes, integrator, res, spp),
                                                     spp, cfg.render_repeats)
            rec["methods"][key] = {"first_s": first, "seconds": med, "image_mean": mean}
            log(f"media {key}: {med:.3f} s (first {first:.2f} s), image mean {mean:.4f}")
    mesh = rec["methods"]["volpath, mesh"]["seconds"]
    for m in rec["methods"].values():
        m["ratio_to_mesh"] = m["seconds"] / mesh
    return rec


# ---- First-image latency ------------------------------------------------------------

def bench_compile(cfg: SpeedConfig, log, variant=VARIANT):
    """Cold and warm first renders of the default scene, each in a subprocess
    sharing one fresh HOME."""
    rec = {"scene": "scenes/cornell.xml", "res": cfg.probe_res, "spp": cfg.probe_spp}
    with tempfile.TemporaryDirectory(prefix="lgshape-speed-home-") as home:
        env = dict(os.environ, HOME=home)
        for key in PROBES:
            cmd = [sys.executable, "-m", "lgshape.bench.probe", CORNELL,
                   str(cfg.probe_res), str(cfg.probe_spp), variant]
            t0 = time.perf_counter()
            try:
                p = subprocess.run(cmd, env=env, capture_output=True, text=True,
                                   timeout=PROBE_TIMEOUT)
            except subprocess.TimeoutExpired:
                rec[key] = {"error": f"over {PROBE_TIMEOUT} s"}
                log(f"first-image latency, {key} cache: over {PROBE_TIMEOUT} s")
                continue
            wall = time.perf_counter() - t0
            if p.returncode != 0:
                err = (p.stderr.strip().splitlines() or ["?"])[-1]
                rec[key] = {"error": err}
                log(f"first-image latency, {key} cache: failed: {err}")
                continue
            r = json.loads(p.stdout.strip().splitlines()[-1])
            r["compile_s"] = r["first_s"] - r["second_s"]
            r["process_s"] = wall
            rec[key] = r
            log(f"first-image latency, {key} cache: first render {r['first_s']:.2f} s, second "
                f"{r['second_s']:.3f} s: compile {r['compile_s']:.2f} s ({r['kernels_compiled']} "
                f"of {r['kernels']} kernels compiled, {_backend(variant)} {r['backend_s']:.2f} s; "
                f"{r['cache_files']} cache files; process {wall:.1f} s)")
    return rec


# ---- Run ----------------------------------------------------------------------------

def run(log=None, quick=False, surfaces=None, cornell=True, compile_latency=True,
        cfg: SpeedConfig | None = None, variant: str = VARIANT) -> dict:
    """The whole section: {"meta", "rows", "cornell", "compile"} (JSON-ready
    apart from inf/NaN, which :func:`lgshape.bench.common.finite` clears)."""
    import mitsuba as mi
    log = log or (lambda msg: print(msg, file=sys.stderr, flush=True))
    cfg = cfg or (QUICK if quick else FULL)
    if surfaces is not None:
        cfg = SpeedConfig(**{**asdict(cfg), "surfaces": tuple(surfaces)})
    mi.set_variant(variant)
    lgshape.register_plugins()
    t_start = time.perf_counter()
    load = os.getloadavg() if hasattr(os, "getloadavg") else ()
    meta = {"quick": bool(quick), "config": asdict(cfg), "variant": variant, "seed": SEED,
            "shadow_offset_diag": SHADOW_OFFSET, "light": {"distance_half_diag": LIGHT_DISTANCE,
                                                           "direction": list(LIGHT_DIR)},
            "st_eps_diag": ST_EPS, "machine": machine(), "git": git_commit(),
            "loadavg_start": " ".join(f"{v:.2f}" for v in load)}
    rows, meshes = [], {}
    for name in cfg.surfaces:
        r, mesh = bench_surface(name, cfg, log, keep_mesh=(name == "tangle" and cornell))
        rows += r
        if mesh is not None:
            meshes[name] = mesh
    out = {"meta": meta, "rows": rows}
    if cornell:
        out["cornell"] = bench_cornell(cfg, log, meshes)
        out["gradients"] = bench_gradients(cfg, log, meshes)
        out["emitters"] = bench_emitters(cfg, log)
        out["media"] = bench_media(cfg, log)
        out["host"] = bench_host(cfg, log)
    meshes.clear()
    if compile_latency:
        out["compile"] = bench_compile(cfg, log, variant)
    load = os.getloadavg() if hasattr(os, "getloadavg") else ()
    meta["loadavg_end"] = " ".join(f"{v:.2f}" for v in load)
    meta["seconds"] = round(time.perf_counter() - t_start, 1)
    return finite(out)


# ---- Chart and report -----------------------------------------------------------

def _mesh_tracer(variant):
    """Mitsuba's ray tracer for meshes on a variant: OptiX on CUDA, else Embree."""
    return "OptiX" if variant.startswith("cuda") else "Embree"


def _backend(variant):
    return "CUDA" if variant.startswith("cuda") else "LLVM"


def chart(results, path):
    """Ratio bars (log scale) per surface, one panel per ray kind, with the
    target lines; a last panel for the cornell render ratio."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    rows = results.get("rows", [])
    surfaces = list(dict.fromkeys(r["surface"] for r in rows))
    cornell = results.get("cornell")
    w = max(4.0, 0.6 * len(surfaces) + 1.5)
    fig, axes = plt.subplots(2, 2, figsize=(2 * w + 1, 8.4), squeeze=False)
    axes = axes.ravel()
    x = np.arange(len(surfaces))
    vals = [v for r in rows for v in (r.get("ratio_sphere"), r.get("ratio_mesh")) if v]
    lo = min(vals + [0.5]) / 1.5
    hi = max(vals + [TARGET_SPHERE]) * 1.5
    for ax, kind in zip(axes, KINDS):
        by = {r["surface"]: r for r in rows if r["kind"] == kind}
        for k, (key, colour, label) in enumerate((
                ("ratio_sphere", "tab:blue", "sphere tracer time / lgshape's"),
                ("ratio_mesh", "tab:brown",
                 f"mesh ({_mesh_tracer(results['meta']['variant'])}) time / lgshape's"))):
            h = [by.get(s, {}).get(key) or np.nan for s in surfaces]
            ax.bar(x + (k - 0.5) * 0.38, h, 0.38, color=colour, label=label)
            for i, s in enumerate(surfaces):      # each bar's target
                t = by.get(s, {}).get("target_sphere" if key == "ratio_sphere"
                                      else "target_mesh")
                if t:
                    ax.plot([x[i] + (k - 1) * 0.38, x[i] + k * 0.38], [t, t], color="k",
                            lw=1.5)
        ax.axhline(1.0, color="0.5", lw=0.8, ls=":")
        ax.set_yscale("log")
        ax.set_ylim(lo, hi)
        ax.set_xticks(x)
        ax.set_xticklabels(surfaces, rotation=60, ha="right", fontsize=8)
        ax.set_title(f"{kind} rays", fontsize=10)
        ax.grid(True, axis="y", which="both", alpha=0.3)
    for ax in axes[:len(KINDS)]:
        ax.set_ylabel("time ratio (above 1: lgshape faster)", fontsize=8)
    axes[0].plot([], [], color="k", lw=1.5, label="target (per bar)")
    axes[0].legend(fontsize=7, loc="upper left")
    if cornell:
        ax = axes[-1]
        ax.bar([0], [cornell["ratio"]], 0.5, color="tab:red")
        ax.axhline(cornell["target"], color="k", lw=1.5)
        ax.set_xticks([0])
        ax.set_xticklabels(["cornell.xml"], fontsize=8)
        ax.set_xlim(-1.5, 1.5)
        ax.set_ylim(0, max(cornell["ratio"], cornell["target"]) * 1.3)
        ax.set_ylabel("render time ratio lg_path / path (mesh)", fontsize=8)
        ax.set_title("render: lg_path time / path's (target: at most the line)", fontsize=10)
        ax.grid(True, axis="y", alpha=0.3)
    else:
        axes[-1].axis("off")
    fig.tight_layout()
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _f(v, fmt="{:.2f}"):
    return "–" if v is None else fmt.format(v)


def _met(v):
    return "–" if v is None else ("yes" if v else "**no**")


def _table(header, rows) -> list[str]:
    """A markdown table (and the blank line after it)."""
    return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)] + \
        ["| " + " | ".join(r) + " |" for r in rows] + [""]


def report(results, chart_path="charts/speed.png") -> list[str]:
    meta, rows = results["meta"], results.get("rows", [])
    cfg = meta["config"]
    L = ["## Speed against the alternatives\n"]
    L.append(f"Rays per second of lgshape (`lgshape.Surface(spec)`, default settings) against "
             f"sphere tracing (valid global Lipschitz bound L of interval arithmetic, eps = "
             f"{meta['st_eps_diag']:g} box diagonals) and a {cfg['mesh_res']}^3 marching-cubes "
             f"mesh of f / |grad f| traced by Mitsuba's {_mesh_tracer(meta['variant'])}, all in "
             "one process and run "
             f"(`{meta['variant']}`, {meta['machine']['nproc']} cores, load average "
             f"{meta['loadavg_start']} at the start and {meta.get('loadavg_end', '?')} at the "
             "end: the cores are shared, so times are noisy). Rays: `camera`, "
             f"{cfg['res']} x {cfg['res']} primary rays (`lgshape.camera`); `incoherent`, "
             f"{cfg['incoherent']} rays with uniform random origins in the box and uniform "
             f"random directions (seed {meta['seed']}); `shadow`, any-hit rays from the points "
             f"lgshape's camera trace hit, {meta['shadow_offset_diag']:g} box diagonals off the "
             "surface along the normal (on the camera's side), towards a point light "
             f"{meta['light']['distance_half_diag']:g} half diagonals from the box centre, "
             "t_max = the distance to the light (lgshape: `.occluded`; sphere tracer: a hit "
             "before t_max; mesh: `scene.ray_test`). lgshape and the sphere tracer run as "
             "frozen functions (`dr.freeze`: recorded once, then replayed without tracing "
             "their Python code again); the mesh's queries are calls into Mitsuba's C++. "
             "A time is the median of "
             f"{cfg['repeats']} samples after a warm-up, each sample repeating the trace for at "
             f"least {cfg['min_sample']} s; the three methods' samples are interleaved (round k "
             "takes one sample of each, in an order that rotates), so that a change in the "
             "shared cores' speed weighs on all of them alike. Ratio = the other method's time "
             "/ lgshape's, the median over the rounds of the ratio within a round (above "
             f"1: lgshape faster). Targets: at least {TARGET_SPHERE:g}x the sphere tracer "
             f"({TARGET_SPHERE_ON_SPHERE:g}x on `sphere`), at least {TARGET_MESH:g}x the mesh. "
             "evals, iterations: per ray (lgshape: point and interval evaluations of f, and "
             "search plus refinement iterations; sphere tracer: its steps); capped: rays at "
             "the iteration cap; agree: the fraction of rays whose hit (occluded) answer is "
             "lgshape's.\n")
    if rows and os.path.basename(chart_path):
        L.append(f"![speed ratios]({chart_path})\n")
    if rows:
        L.append("| surface | ray kind | rays | lgshape Mrays/s | evals | iterations | capped | "
                 "sphere tracer Mrays/s | steps | capped | agree | ratio | target | met | "
                 "mesh Mrays/s | agree | ratio | target | met |")
        L.append("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
        for r in rows:
            lg, sp, me = r["lgshape"], r.get("sphere_trace") or {}, r.get("mesh") or {}
            L.append(f"| {r['surface']} | {r['kind']} | {r['rays']} | "
                     f"{_f(lg.get('mrays_per_s'))} | {_f(lg.get('evals_per_ray'), '{:.1f}')} | "
                     f"{_f(lg.get('iterations_per_ray'), '{:.1f}')} | "
                     f"{_f(lg.get('capped'), '{}')} | "
                     f"{_f(sp.get('mrays_per_s'))} | {_f(sp.get('evals_per_ray'), '{:.1f}')} | "
                     f"{_f(sp.get('capped'), '{}')} | {_f(sp.get('agree'), '{:.4f}')} | "
                     f"{_f(r['ratio_sphere'])} | >= {r['target_sphere']:g} | "
                     f"{_met(r['met_sphere'])} | {_f(me.get('mrays_per_s'))} | "
                     f"{_f(me.get('agree'), '{:.4f}')} | {_f(r['ratio_mesh'])} | "
                     f">= {r['target_mesh']:g} | {_met(r['met_mesh'])} |")
        L.append("")
        for key, what in (("met_sphere", "the sphere-tracer target"),
                          ("met_mesh", "the mesh target")):
            judged = [r for r in rows if r[key] is not None]
            met = [r for r in judged if r[key]]
            L.append(f"- {what}: met on {len(met)} of {len(judged)} (surface, rays) pairs"
                     + "".join(f"; {k}: {sum(1 for r in met if r['kind'] == k)} of "
                               f"{sum(1 for r in judged if r['kind'] == k)}" for k in KINDS)
                     + ".")
        for kind in KINDS:
            sel = [r for r in rows if r["kind"] == kind]
            for key, what in (("ratio_sphere", "sphere tracer"), ("ratio_mesh", "mesh")):
                v = [r[key] for r in sel if r[key]]
                if v:
                    geo = math.exp(sum(math.log(x) for x in v) / len(v))
                    L.append(f"- {kind} rays, {what}: ratio {min(v):.2f} to {max(v):.2f}, "
                             f"geometric mean {geo:.2f} over {len(v)} surfaces.")
        bad = [r for r in rows if (r.get("sphere_trace") or {}).get("agree") is not None
               and r["sphere_trace"]["agree"] < AGREE_NOTE]
        if bad:
            L.append(f"- The sphere tracer disagrees with lgshape on more than "
                     f"{1 - AGREE_NOTE:.0%} of the rays on: " + ", ".join(
                         f"{r['surface']} {r['kind']} ({1 - r['sphere_trace']['agree']:.1%}, "
                         f"{r['sphere_trace']['capped']} capped)" for r in bad)
                     + ". There its time is that of wrong answers: with a global L far above "
                     "|grad f| near the surface, |f| / L falls below eps before the surface "
                     "(false hits, a false occlusion at the start of a shadow ray) or the "
                     "steps shrink until the 1024-step cap.")
        L.append("")
    c = results.get("cornell")
    if c:
        L.append("### Render: cornell.xml\n")
        L.append(f"`{c['scene']}` rendered by `lg_path` as it is, against the same scene with "
                 f"the {', '.join(c['meshed'])} replaced by its {c['mesh_res']}^3 marching-cubes "
                 f"mesh ({', '.join(str(v) for v in c['triangles'].values())} triangles, a PLY "
                 "file, same to_world and BSDF, normals towards f > 0) rendered by Mitsuba's "
                 f"`path` (same max_depth): {c['res']} x {c['res']} pixels, {c['spp']} spp, the "
                 f"median of {c['repeats']} `mi.render` calls after a warm-up render. The image "
                 "means show that both scenes render the same picture (up to noise and the "
                 "mesh's approximation).\n")
        L.append("| integrator | first render s | render s (median) | image mean |")
        L.append("|---|---|---|---|")
        for key, what in (("lg_path", "lg_path, lgsurface"), ("path", "path, mesh")):
            r = c[key]
            L.append(f"| {what} | {r['first_s']:.2f} | {r['seconds']:.3f} | "
                     f"{r['image_mean']:.4f} |")
        L.append("")
        L.append(f"Ratio lg_path / path: **{c['ratio']:.2f}** (target at most "
                 f"{c['target']:g}: {_met(c['met'])}).\n")
    gr = results.get("gradients")
    if gr:
        L.append("### Inverse rendering: gradient pass against primal\n")
        L.append(f"`{gr['scene']}` at {gr['res']} x {gr['res']}, {gr['spp']} spp: a primal "
                 "render and a gradient pass (`mi.render` with the parameters differentiable, "
                 "then `dr.backward` of the image mean), the cases interleaved round by round, "
                 f"medians of {gr['repeats']} rounds; `prb` renders the same scene with the "
                 f"tangle as a marching-cubes mesh ({gr['mesh_res']}^3 samples); the last row "
                 "without lg_prb's shadow-edge term.\n")
        L += _table(("integrator", "parameters", "primal s", "gradient pass s", "ratio",
                     "rounds' ratios"),
                    [(key.split("_shape")[0] + (", shadow_edges false" if "no_shadow" in key
                                                 else ""), ", ".join(r["parameters"]),
                      f"{r['primal_s']:.3f}", f"{r['gradient_s']:.3f}", f"{r['ratio']:.2f}",
                      (f"{min(r['ratios']):.2f}-{max(r['ratios']):.2f}"
                       if r.get("ratios") else ""))
                     for key, r in ((k, gr.get(k)) for k in ("lg_prb", "prb", "lg_prb_shape",
                                                          "lg_prb_shape_no_shadow_edges"))
                     if r])
        L.append(f"lg_prb's ratio {gr['lg_prb']['ratio']:.2f} against prb's "
                 f"{gr['prb']['ratio']:.2f} ({'met' if gr['met_anchor'] else 'not met'}: no "
                 f"worse than prb's), and at most {gr['target_ratio']:g} "
                 f"({'met' if gr['met_ratio'] else 'not met'}; with the tangle's to_world "
                 f"{gr['lg_prb_shape']['ratio']:.2f}, "
                 f"{'met' if gr.get('met_ratio_shape') else 'not met'}).\n")
    em = results.get("emitters")
    if em:
        L.append("### Emitting lgsurfaces: noise against Mitsuba's emitters\n")
        L.append(f"An emitting sphere (radius 0.3) over a diffuse floor, {em['res']} x "
                 f"{em['res']}, {em['spp']} spp, {em['seeds']} seeds: the image MSE against "
                 f"Mitsuba's path with the native emitting sphere at {em['reference_spp']} spp. "
                 "lg_path samples the lgsurface in the cone of its bounding sphere; Mitsuba's "
                 "sphere samples its visible cap, the mesh "
                 f"({em['mesh_triangles']} triangles) its area.\n")
        def noise_table(methods):
            return _table(("method", "MSE", "render s", "MSE / native", "at equal time"),
                          [(key, f"{m['mse']:.3e}", f"{m['seconds']:.3f}",
                            f"{m['mse_ratio']:.2f}", f"{m['mse_ratio_equal_time']:.2f}")
                           for key, m in methods.items()])
        L += noise_table(em["methods"])
        if em.get("textured"):
            L.append("The same with a textured radiance (a checkerboard of 0.5 and 6 on a "
                     "12 x 6 grid of uv; the reference renders it the same way):\n")
            L += noise_table(em["textured"])
    ho = results.get("host")
    if ho:
        L.append("### Host time per render\n")
        L.append(f"The emitter scene at {ho['res']} x {ho['res']}, {ho['spp']} spp (a size where "
                 "the host's work is most of a render): lg_path with the lamp an lgsurface, as "
                 "it renders (frozen renders) and with every render traced "
                 "(`LGSHAPE_NO_FREEZE=1`), against Mitsuba's path with the native sphere; "
                 f"medians of {ho['rounds']} interleaved rounds after three warm-up renders each. "
                 "`kernels ms` is the kernels' execution time from Dr.Jit's kernel history; "
                 f"the rest is the host's. Target: lg_path / path at most {TARGET_HOST:g}: "
                 f"{'met' if ho['met'] else 'not met'}.\n")
        L += _table(("method", "ms a render", "kernels ms", "host ms", "/ path",
                     "kernels compiled after warm-up", "image mean"),
                    [(key, f"{m['seconds'] * 1e3:.1f}", f"{m['kernel_s'] * 1e3:.1f}",
                      f"{m['host_s'] * 1e3:.1f}", f"{m['ratio']:.2f}",
                      str(m["compiled_after_warmup"]), f"{m['image_mean']:.4f}")
                     for key, m in ho["methods"].items()])
    md = results.get("media")
    if md:
        L.append("### Media: lg_volpath against volpath\n")
        L.append(f"A scattering medium inside a sphere (null boundary) over a floor, {md['res']} x "
                 f"{md['res']}, {md['spp']} spp, medians of {md['repeats']} renders: lg_volpath "
                 "with the sphere as an lgsurface, Mitsuba's volpath with its native sphere and "
                 f"with a marching-cubes mesh ({md['mesh_triangles']} triangles).\n")
        L += _table(("method", "render s", "first s", "/ mesh", "image mean"),
                    [(key, f"{m['seconds']:.3f}", f"{m['first_s']:.2f}",
                      f"{m['ratio_to_mesh']:.2f}", f"{m['image_mean']:.4f}")
                     for key, m in md["methods"].items()])
    k = results.get("compile")
    if k:
        L.append("### First-image latency\n")
        L.append(f"`{k['scene']}` (`make render`'s scene) at {k['res']} x {k['res']}, "
                 f"{k['spp']} spp, in a subprocess with HOME set to a fresh temporary folder "
                 "(Dr.Jit's kernel cache, `$HOME/.drjit`, starts empty): the first `mi.render` "
                 "minus a second identical render in the same process is the kernel compile "
                 f"time (`{_backend(meta['variant'])} compile s`: the backend time of the kernels "
                 "compiled, from Dr.Jit's "
                 "kernel history). Two more subprocesses with the same HOME repeat it with the "
                 "kernels cached by the earlier ones (kernels reused across runs).\n")
        L.append("| kernel cache | import s | scene load s | first render s | second render s | "
                 "compile s (first - second) | kernels compiled / launched | "
                 f"{_backend(meta['variant'])} compile s | "
                 "cache files after |")
        L.append("|---|---|---|---|---|---|---|---|---|")
        for key in PROBES:
            r = k.get(key)
            if r is None:
                continue
            if "error" in r:
                L.append(f"| {key} | {r['error']} ||||||||")
                continue
            L.append(f"| {key.replace('_', ' ')} | {_f(r.get('import_s'))} | "
                     f"{_f(r.get('load_s'))} | {_f(r.get('first_s'))} | "
                     f"{_f(r.get('second_s'), '{:.3f}')} | {_f(r.get('compile_s'))} | "
                     f"{_f(r.get('kernels_compiled'), '{}')} / {_f(r.get('kernels'), '{}')} | "
                     f"{_f(r.get('backend_s'))} | {_f(r.get('cache_files'), '{}')} |")
        L.append("")
        warm = [key for key in PROBES[1:] if (k.get(key) or {}).get("kernels_compiled")]
        if warm:
            L.append(f"With the cache filled, the {' and '.join(warm)} run(s) still compiled "
                     "kernels: their IR differed from the cached kernels' (a literal that is "
                     "not the same in every process), so the cache could not serve them.\n")
    return L


# ---- Command line ---------------------------------------------------------------------

def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    p = argparse.ArgumentParser(prog="python -m lgshape.bench.speed",
                                description="The speed section of the benchmark.")
    p.add_argument("--out", required=True)
    p.add_argument("--quick", action="store_true")
    p.add_argument("--surfaces", nargs="+", choices=sorted(LIBRARY), metavar="NAME")
    p.add_argument("--no-cornell", dest="cornell", action="store_false")
    p.add_argument("--no-compile", dest="compile", action="store_false")
    p.add_argument("--variant", default=VARIANT,
                   help=f"Mitsuba variant, a JIT one (default: {VARIANT}; cuda_ad_rgb on a GPU)")
    p.add_argument("--res", type=int, metavar="N",
                   help="camera rays N x N (default 512; a GPU needs more rays than a "
                        "wave of its threads for the launch's fixed costs not to dominate)")
    p.add_argument("--incoherent", type=int, metavar="N", help="incoherent rays (default 262144)")
    args = p.parse_args(argv)
    for name in ("res", "incoherent"):
        v = getattr(args, name)
        if v is not None and v < 1:
            p.error(f"--{name} must be a positive integer, not {v}")
    base = QUICK if args.quick else FULL
    cfg = SpeedConfig(**{**asdict(base), **{k: getattr(args, k) for k in ("res", "incoherent")
                                            if getattr(args, k) is not None}})
    log = stderr_log()
    results = run(log, quick=args.quick, surfaces=args.surfaces, cornell=args.cornell,
                  compile_latency=args.compile, cfg=cfg, variant=args.variant)
    os.makedirs(os.path.join(args.out, "charts"), exist_ok=True)
    chart(results, os.path.join(args.out, "charts", "speed.png"))
    with open(os.path.join(args.out, "speed.json"), "w") as fh:
        json.dump(results, fh, indent=1, allow_nan=False)
    with open(os.path.join(args.out, "SPEED.md"), "w") as fh:
        fh.write("\n".join(report(results)) + "\n")
    log(f"wrote {args.out}/speed.json, SPEED.md and charts/speed.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
