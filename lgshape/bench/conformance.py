"""Conformance of the lg integrators against Mitsuba's own, pixel by pixel.

Every case is a scene whose lgsurfaces all have a native twin (a sphere, a
rectangle, a cube, a disk: :func:`twin`), built twice, once with the
lgsurfaces and once with the twins. Each lg integrator renders the first,
its Mitsuba counterpart (``lg_path``/``path``, ``lg_prb``/``prb``,
``lg_volpath``/``volpath``, ``lg_direct``/``direct``, ``lg_aov``/``aov``)
the second, over K independent seeds each (disjoint seeds: the two sets of
images are independent). :func:`compare` then tests, at four scales, that
the two estimators have the same expectation: every pixel and channel,
every block of pixels, the image mean of each channel (Welch's t with
Satterthwaite's degrees of freedom over the per-seed values), and the
mean of the blocks' standardized differences (a systematic bias too small
to show in any one pixel). Each scale gets a quarter of the comparison's
false-alarm budget, split over its tests (Bonferroni), and the run's
budget :data:`ALPHA` is split over its comparisons; so a run without a
bug fails with probability at most ALPHA, whatever the machine.

The tests (tests/test_54_conformance.py) run the cases small; the
benchmark (:func:`run`, ``lgshape bench``) runs them larger and reports,
per comparison, the tests flagged at each scale and the largest |z|.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

#: The false-alarm probability of a whole run (all comparisons together).
ALPHA = 1e-3

#: Two renders of the same expectation may also differ by float32
#: rounding where the noise vanishes (a pixel that sees only a constant
#: emitter, an AOV): ROUND u (|a| + |b| + s), u = 2^-24, s the channel's
#: largest |value| in the image (a pixel value is a sum of float32 terms of
#: a few dozen roundings each, relative to the size of the quantity: a
#: component of a unit normal near 0 carries the rounding of the vector's
#: other components; the lgsurface's hits are within the search's tolerance
#: of the twin's), added to the standard error.
ROUND, U = 256, 2.0 ** -24

#: The pixel blocks of the second scale (block x block pixels).
BLOCK = 4


# ---------------------------------------------------------------------------
#  Twins: an lgsurface and the native shape it equals
# ---------------------------------------------------------------------------

#: The half thickness of the lgsurface disk (a flat cylinder: f cannot
#: bound an open disk inside a box); its rim, 2 h high, is 2 h / r of the
#: disk's area.
DISK_H = 1e-4


def twin(kind: str, lg: bool, to_world=None, **props) -> dict:
    """The shape ``kind`` as an lgsurface (``lg``) or as Mitsuba's native
    shape: ``sphere`` (radius 1 about the origin: Mitsuba's sphere, uv
    included), ``rectangle`` (z = 0, |x|, |y| <= 1, normal +z), ``cube``
    ([-1, 1]^3, outward normals) and ``disk`` (z = 0, radius 1, normal +z;
    the lgsurface is the cylinder |z| <= DISK_H whose face z = -DISK_H,
    normal -z, stands for a native disk there with flipped normals: a disk
    seen and emitting downward). ``to_world`` places either; ``props``
    (bsdf, emitter, media, flip_normals) go to both."""
    import mitsuba as mi
    T = mi.ScalarTransform4f
    to_world = T() if to_world is None else to_world
    if not lg:
        if kind == "disk":
            props = {**props, "flip_normals": not props.get("flip_normals", False)}
            to_world = to_world @ T().translate([0, 0, -DISK_H])
        return {"type": kind, "to_world": to_world, **props}
    if kind == "sphere":
        body = {"surface": "sphere", "radius": 1.0}
    elif kind == "rectangle":
        body = {"expr": "z", "bbox_min": [-1, -1, -0.01], "bbox_max": [1, 1, 0.01]}
    elif kind == "cube":
        body = {"expr": "max(abs(x), max(abs(y), abs(z))) - 1", "bbox_min": [-1.1] * 3,
                "bbox_max": [1.1] * 3}
    elif kind == "disk":
        body = {"expr": f"max(abs(z) - {DISK_H!r}, sqrt(x^2 + y^2) - 1)",
                "bbox_min": [-1.05, -1.05, -4 * DISK_H], "bbox_max": [1.05, 1.05, 4 * DISK_H]}
    else:
        raise ValueError(f"twin: unknown kind '{kind}' (sphere, rectangle, cube, disk)")
    return {"type": "lgsurface", **body, "to_world": to_world, **props}


# ---------------------------------------------------------------------------
#  The cases
# ---------------------------------------------------------------------------

#: The lg integrators' Mitsuba counterparts.
NATIVE = {"lg_path": "path", "lg_prb": "prb", "lg_volpath": "volpath",
          "lg_direct": "direct", "lg_aov": "aov"}


@dataclass
class Case:
    """A scene (``shapes(lg)``: its shapes, emitters and media as dict
    entries, the lgsurfaces as lgsurfaces or as their twins) and the
    integrators that render it: (lg integrator, its properties); the
    counterpart is :data:`NATIVE`'s. ``sensor``: extra sensor properties
    (e.g. its medium), ``origin`` / ``target`` the camera; ``quick``: in
    the tests and ``lgshape bench --quick``."""
    name: str
    shapes: Callable
    integrators: list
    what: str
    origin: tuple = (0.0, 0.5, 3.0)
    target: tuple = (0.0, 0.0, 0.0)
    fov: float = 45.0
    sensor: Callable = None
    quick: bool = False              # in the tests (and bench --quick)


def _T():
    import mitsuba as mi
    return mi.ScalarTransform4f


def _rgb(*v):
    return {"type": "rgb", "value": list(v) if len(v) > 1 else v[0]}


def _diffuse(*v):
    return {"type": "diffuse", "reflectance": _rgb(*v)}


def _floor(lg=False, kind="rectangle", bsdf=None):
    T = _T()
    return twin(kind, lg, T().translate([0, -0.3, 0]) @ T().rotate([1, 0, 0], -90) @ T().scale(2),
                bsdf=bsdf or _diffuse(0.6))


def _ball(lg, centre=(0, 0.1, 0), r=0.4, **props):
    T = _T()
    return twin("sphere", lg, T().translate(list(centre)) @ T().scale(r), **props)


def _lamp(lg, centre=(0, 0.45, 0), r=0.25, radiance=4.0, **props):
    return _ball(lg, centre, r, emitter={"type": "area", "radiance": _rgb(radiance)}, **props)


def _area(radiance):
    return {"type": "area", "radiance": _rgb(radiance)}


def _envmap():
    """A small raw envmap (an RGB gradient with a bright patch)."""
    import mitsuba as mi
    h, w = 8, 16
    v, u = np.meshgrid(np.linspace(0, 1, h), np.linspace(0, 1, w), indexing="ij")
    img = np.stack([0.2 + 0.6 * u, 0.3 + 0.5 * (1 - v), 0.4 + 0.2 * u * v], -1)
    img[1:3, 3:6] = [6.0, 5.0, 4.0]
    return {"type": "envmap", "bitmap": mi.Bitmap(img.astype(np.float32))}


def _bitmap(seed=3, h=4, w=8, lo=0.1, hi=0.9):
    import mitsuba as mi
    texels = np.random.default_rng(seed).uniform(lo, hi, (h, w, 3)).astype(np.float32)
    return {"type": "bitmap", "bitmap": mi.Bitmap(texels), "raw": True, "filter_type": "nearest"}


def _normal_bitmap():
    """A tangent-space normal map (raw, bilinear): tilted normals in [0, 1]^3."""
    import mitsuba as mi
    rng = np.random.default_rng(5)
    n = np.concatenate([rng.uniform(-0.5, 0.5, (4, 8, 2)), np.ones((4, 8, 1))], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return {"type": "bitmap", "bitmap": mi.Bitmap((0.5 * n + 0.5).astype(np.float32)),
            "raw": True}


def _height_bitmap():
    import mitsuba as mi
    hgt = np.random.default_rng(6).uniform(0, 1, (8, 16, 1)).astype(np.float32)
    return {"type": "bitmap", "bitmap": mi.Bitmap(hgt), "raw": True}


def _fog(id_="fog"):
    return {"type": "homogeneous", "id": id_, "sigma_t": 1.5, "albedo": _rgb(0.8, 0.6, 0.4)}


PATHS = [("lg_path", {"max_depth": 4}), ("lg_prb", {"max_depth": 4})]
ALL_FOUR = PATHS + [("lg_direct", {}), ("lg_volpath", {"max_depth": 4})]


def _hidden(integrators):
    return [(k, {**p, "hide_emitters": True}) for k, p in integrators]


def cases() -> list:
    """Every case of the suite (the quick ones first)."""
    T = _T()
    sky = {"type": "constant", "radiance": _rgb(0.3, 0.35, 0.45)}
    out = [
        # ---- hide_emitters with every emitter kind ----
        Case("hidden_sky", lambda lg: {"sky": sky, "floor": _floor(lg), "ball": _ball(lg)},
             _hidden(ALL_FOUR), "hide_emitters, a constant sky seen directly", quick=True),
        Case("hidden_envmap", lambda lg: {"env": _envmap(), "floor": _floor(),
                                          "ball": _ball(lg, bsdf=_diffuse(0.5, 0.6, 0.7))},
             _hidden(PATHS), "hide_emitters, an envmap"),
        Case("hidden_lg_lamp", lambda lg: {"floor": _floor(), "lamp": _lamp(lg),
                                           "ball": _ball(lg, (0.5, -0.1, 0.3), 0.2)},
             _hidden(ALL_FOUR), "hide_emitters, an emitting lgsurface seen directly"),
        Case("hidden_native_lamp", lambda lg: {
            "floor": _floor(lg), "ball": _ball(lg, (0.3, 0.0, 0.2), 0.3),
            "panel": {"type": "rectangle", "emitter": _area(6.0),
                      "to_world": T().translate([-0.4, 0.9, -0.3]) @ T().rotate([1, 0, 0], 60)
                      @ T().scale(0.4)}},
             _hidden(PATHS + [("lg_direct", {})]), "hide_emitters, a native area light"),
        # ---- emitters behind and inside other surfaces ----
        Case("lamp_behind_null", lambda lg: {
            "floor": _floor(), "lamp": _lamp(lg),
            "veil": twin("rectangle", lg, T().rotate([1, 0, 0], -90) @ T().scale(1.2),
                         bsdf={"type": "null"})},
             ALL_FOUR, "an emitting lgsurface seen through a null rectangle", quick=True),
        Case("lamp_in_glass", lambda lg: {
            "sky": {"type": "constant", "radiance": _rgb(0.1)}, "floor": _floor(),
            "lamp": _lamp(lg, (0, 0.2, 0), 0.12, 8.0),
            "shell": _ball(lg, (0, 0.2, 0), 0.35, bsdf={"type": "dielectric", "int_ior": 1.4})},
             [("lg_path", {"max_depth": 8}), ("lg_prb", {"max_depth": 8}),
              ("lg_volpath", {"max_depth": 8})], "an emitting sphere inside a glass sphere"),
        Case("lamp_under_roughglass", lambda lg: {
            "floor": _floor(), "lamp": _lamp(lg, (0, 0.6, 0), 0.2, 6.0),
            "pane": twin("rectangle", lg, T().translate([0, 0.25, 0]) @ T().rotate([1, 0, 0], -90)
                         @ T().scale(0.8),
                         bsdf={"type": "roughdielectric", "alpha": 0.2, "int_ior": 1.5})},
             ALL_FOUR[:3], "an emitting sphere over a rough dielectric pane"),
        Case("lamp_back_sides", lambda lg: {
            "floor": _floor(lg),
            "panel": twin("rectangle", lg, T().translate([0.0, 0.5, -0.2])
                          @ T().rotate([1, 0, 0], 130) @ T().scale(0.5), emitter=_area(5.0),
                          bsdf={"type": "twosided", "bsdf": _diffuse(0.7)}),
            "inward": _lamp(lg, (0.6, 0.0, 0.3), 0.2, 3.0, flip_normals=True),
            "sky": {"type": "constant", "radiance": _rgb(0.05)}},
             ALL_FOUR, "a tilted emitting rectangle facing away (its back seen) and a sphere that emits "
             "inwards (flip_normals), two-sided BSDF", quick=True),
        Case("disk_lamp", lambda lg: {
            "floor": _floor(), "ball": _ball(False, (0.3, -0.1, 0.2), 0.2),
            "disk": twin("disk", lg, T().translate([0, 0.7, 0]) @ T().rotate([1, 0, 0], -90)
                         @ T().scale(0.4), emitter=_area(6.0))},
             [("lg_path", {"max_depth": 3}), ("lg_direct", {})],
             "an emitting disk facing down", quick=True),
        # ---- media ----
        Case("fog_ball_lamp", lambda lg: {
            "sky": {"type": "constant", "radiance": _rgb(0.2)}, "floor": _floor(),
            "lamp": _lamp(lg, (0.0, 0.1, 0.0), 0.1, 8.0),
            "cloud": _ball(lg, (0, 0.1, 0), 0.45, bsdf={"type": "null"}, interior=_fog())},
             [("lg_volpath", {"max_depth": 8})], "an emitting sphere inside fog behind a null "
             "boundary"),
        Case("absorbing_glass", lambda lg: {
            "sky": sky, "floor": _floor(lg),
            "lamp": {"type": "point", "position": [1.0, 1.5, 1.0], "intensity": _rgb(6.0)},
            "ball": _ball(lg, bsdf={"type": "dielectric", "int_ior": 1.5}, interior={
                "type": "homogeneous", "sigma_t": _rgb(0.15, 0.5, 1.0), "scale": 3.0,
                "albedo": 0.0})},
             [("lg_volpath", {"max_depth": 8})], "glass with an absorbing interior"),
        Case("camera_in_fog", lambda lg: {
            "fog": _fog(), "floor": _floor(),
            "lamp": {"type": "point", "position": [0.3, 0.6, 0.4], "intensity": _rgb(3.0)},
            "room": _ball(lg, (0, 0.3, 0.8), 1.5, bsdf={"type": "null"},
                          interior={"type": "ref", "id": "fog"}),
            "sky": {"type": "constant", "radiance": _rgb(0.2)}},
             [("lg_volpath", {"max_depth": 6})], "the camera inside a medium bounded by a "
             "null sphere", origin=(0, 0.5, 1.6),
             sensor=lambda: {"medium": {"type": "ref", "id": "fog"}}, quick=True),
        # ---- BSDFs: textures, normal and bump maps, conductors, plastic ----
        Case("textured", lambda lg: {
            "sky": sky, "floor": _floor(),
            "lamp": {"type": "point", "position": [1.0, 1.5, 1.5], "intensity": _rgb(5.0)},
            "ball": _ball(lg, bsdf={"type": "diffuse", "reflectance": _bitmap()})},
             PATHS[:1] + [("lg_aov", {"aovs": "uv:uv,n:sh_normal"})],
             "a uv-textured sphere", quick=True),
        Case("normal_and_bump", lambda lg: {
            "sky": sky, "floor": _floor(),
            "lamp": {"type": "spot", "to_world": T().look_at([1, 1.5, 1.5], [0, 0, 0], [0, 1, 0]),
                     "intensity": _rgb(12.0), "cutoff_angle": 40},
            "a": _ball(lg, (-0.45, 0.0, 0), 0.3, bsdf={
                "type": "normalmap", "normalmap": _normal_bitmap(), "bsdf": _diffuse(0.7)}),
            "b": _ball(lg, (0.45, 0.0, 0), 0.3, bsdf={
                "type": "bumpmap", "arbitrary": _height_bitmap(), "scale": 0.5,
                "bsdf": {"type": "roughconductor", "alpha": 0.3}})},
             PATHS, "normal-mapped and bump-mapped spheres under a spot light"),
        Case("conductors_plastic", lambda lg: {
            "env": _envmap(), "floor": _floor(lg, bsdf={"type": "plastic"}),
            "a": _ball(lg, (-0.45, 0.0, 0), 0.3, bsdf={
                "type": "roughconductor", "material": "Au", "distribution": "ggx",
                "alpha_u": 0.05, "alpha_v": 0.4}),
            "b": twin("cube", lg, T().translate([0.45, -0.05, 0]) @ T().rotate([0, 1, 0], 30)
                      @ T().scale(0.25), bsdf={"type": "roughplastic", "alpha": 0.2})},
             PATHS + [("lg_direct", {})], "an anisotropic rough conductor sphere and a rough "
             "plastic cube under an envmap"),
        # ---- light types ----
        Case("lights", lambda lg: {
            "floor": _floor(lg), "ball": _ball(lg, (-0.3, 0.0, 0), 0.3),
            "box": twin("cube", lg, T().translate([0.45, -0.1, 0.1]) @ T().scale(0.2)),
            "point": {"type": "point", "position": [-1.0, 1.2, 1.0], "intensity": _rgb(3.0)},
            "sun": {"type": "directional", "direction": [0.3, -1, -0.4], "irradiance": _rgb(1.0)},
            "spot": {"type": "spot", "to_world": T().look_at([1, 1.2, 1], [0, 0, 0], [0, 1, 0]),
                     "intensity": _rgb(6.0), "cutoff_angle": 25}},
             ALL_FOUR, "point, directional and spot lights on a sphere, a cube and the floor"),
        # ---- depth limits ----
        Case("depths", lambda lg: {
            "sky": sky, "floor": _floor(lg), "lamp": _lamp(lg, (-0.4, 0.4, -0.3), 0.15, 6.0),
            "ball": _ball(lg, (0.25, 0.0, 0.1), 0.3, bsdf=_diffuse(0.8))},
             [("lg_path", {"max_depth": 1}), ("lg_prb", {"max_depth": 2}),
              ("lg_path", {"max_depth": 7, "rr_depth": 1}), ("lg_prb", {"max_depth": -1,
                                                                        "rr_depth": 2}),
              ("lg_volpath", {"max_depth": 2})],
             "max_depth 1, 2, 7 and unbounded, Russian roulette from depth 1 and 2"),
        # ---- several overlapping lgsurfaces ----
        Case("overlapping", lambda lg: {
            "sky": sky, "floor": _floor(lg),
            "a": _ball(lg, (-0.15, 0.05, 0), 0.35, bsdf=_diffuse(0.8, 0.3, 0.2)),
            "b": _ball(lg, (0.2, 0.1, 0.1), 0.3, bsdf=_diffuse(0.2, 0.7, 0.3)),
            "c": twin("cube", lg, T().translate([0.05, -0.15, 0.15]) @ T().scale(0.2),
                      bsdf=_diffuse(0.3, 0.3, 0.9)),
            "lamp": _lamp(lg, (0.6, 0.7, 0.4), 0.12, 10.0)},
             PATHS + [("lg_direct", {}), ("lg_aov", {"aovs": "d:depth,p:position,g:geo_normal"})],
             "two overlapping spheres and a cube through them, one emitting sphere"),
        # ---- the camera inside a surface ----
        Case("inside_sphere", lambda lg: {
            "room": _ball(lg, (0, 0, 0), 1.5, flip_normals=True, bsdf=_diffuse(0.6)),
            "box": twin("cube", lg, T().translate([0.2, -0.6, -0.5]) @ T().scale(0.3)),
            "lamp": _lamp(lg, (-0.5, 0.6, -0.4), 0.15, 8.0)},
             PATHS + [("lg_direct", {})], "the camera inside a sphere (flipped normals) with an "
             "emitting sphere", origin=(0, 0.2, 1.0)),
    ]
    return out


# ---------------------------------------------------------------------------
#  Rendering
# ---------------------------------------------------------------------------

def scene_dict(case: Case, integrator: str, props: dict, lg: bool, res: int, spp: int) -> dict:
    import mitsuba as mi
    native_props = dict(props)
    kind = integrator if lg else NATIVE[integrator]
    sensor = {"type": "perspective", "fov": case.fov,
              "to_world": mi.ScalarTransform4f().look_at(list(case.origin), list(case.target),
                                                         [0, 1, 0]),
              "film": {"type": "hdrfilm", "width": res, "height": res,
                       "rfilter": {"type": "box"}},
              "sampler": {"type": "independent", "sample_count": spp}}
    if case.sensor is not None:
        sensor.update(case.sensor())
    return {"type": "scene", "integrator": {"type": kind, **native_props}, "sensor": sensor,
            **case.shapes(lg)}


def render_seeds(case, integrator, props, lg, res, spp, seeds) -> np.ndarray:
    """The images of ``seeds`` (an iterable of ints): [K, H, W, C] float64."""
    import mitsuba as mi
    import warnings
    scene = mi.load_dict(scene_dict(case, integrator, props, lg, res, spp))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")              # (lgshape's media warnings)
        return np.stack([np.array(mi.render(scene, seed=int(s)), np.float64) for s in seeds])


# ---------------------------------------------------------------------------
#  The statistics
# ---------------------------------------------------------------------------

def welch(xa, xb, scale=0.0):
    """Welch's t of mean(xa) - mean(xb) over the first axis (the seeds),
    with the rounding floor (:data:`ROUND`; ``scale``: each channel's
    largest |value|, broadcast against the means) in the standard error:
    (t, df). Lanes where both are constant and equal have t = 0."""
    ka, kb = xa.shape[0], xb.shape[0]
    ma, mb = xa.mean(0), xb.mean(0)
    va, vb = xa.var(0, ddof=1) / ka, xb.var(0, ddof=1) / kb
    floor = (ROUND * U * (np.abs(ma) + np.abs(mb) + scale)) ** 2
    d = ma - mb
    se2 = va + vb + floor
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(d == 0, 0.0, d / np.sqrt(se2))
        df = (va + vb) ** 2 / (va ** 2 / (ka - 1) + vb ** 2 / (kb - 1))
    df = np.where(np.isfinite(df) & (df > 0), df, ka + kb - 2)
    df = np.clip(df, min(ka, kb) - 1, ka + kb - 2)
    return t, df


def _blocks(x, block):
    k, h, w, c = x.shape
    hb, wb = h // block, w // block
    x = x[:, :hb * block, :wb * block]
    return x.reshape(k, hb, block, wb, block, c).mean((2, 4))


@dataclass
class Verdict:
    """One comparison's result: per scale (pixel, block, image, mean), the
    number of tests and of flagged ones, the largest |z| (the two-sided
    p-value's normal equivalent) and where."""
    scales: dict = field(default_factory=dict)
    threshold_z: dict = field(default_factory=dict)

    @property
    def flagged(self):
        return sum(s["flagged"] for s in self.scales.values())

    def summary(self):
        return ", ".join(f"{k}: {s['flagged']}/{s['tests']} flagged, max |z| {s['max_z']:.2f}"
                         f" (limit {self.threshold_z[k]:.2f}) at {s['where']}"
                         for k, s in self.scales.items())


def _z_of_p(p):
    from scipy.stats import norm
    return norm.isf(np.maximum(p, 1e-300) / 2)


def compare(a, b, alpha, block=BLOCK) -> Verdict:
    """Test that the per-seed images ``a`` and ``b`` ([K, H, W, C]) have the
    same expectation, at false-alarm probability ``alpha`` in all: a
    quarter of it to each scale (pixels, blocks, channels' image means, the
    mean of the blocks' standardized differences), split evenly over the
    scale's tests. The mean scale: the blocks' t summed, standardized."""
    from scipy.stats import norm, t as student
    verdict = Verdict()
    size = np.maximum(np.abs(a).max((0, 1, 2)), np.abs(b).max((0, 1, 2)))   # per channel
    for scale, (xa, xb) in (("pixel", (a, b)), ("block", (_blocks(a, block), _blocks(b, block))),
                            ("image", (a.mean((1, 2)), b.mean((1, 2))))):
        t, df = welch(xa, xb, size)
        p = 2 * student.sf(np.abs(t), df)
        n = p.size
        limit = alpha / 4 / n
        worst = np.unravel_index(np.argmin(p), p.shape)
        verdict.scales[scale] = {"tests": int(n), "flagged": int(np.sum(p < limit)),
                                 "max_z": float(_z_of_p(p[worst])),
                                 "where": tuple(int(i) for i in worst)}
        verdict.threshold_z[scale] = float(_z_of_p(limit))
        if scale == "block":
            t_blk, df_blk = t, df
    # The blocks' t are independent (disjoint samples), each of variance
    # df / (df - 2): their sum, standardized, is close to normal. (Blocks,
    # not pixels: where the two estimators' distributions differ in
    # skewness, the mean of t is not 0, and it shrinks with the samples
    # each t averages.)
    var = np.where(df_blk > 2, df_blk / np.maximum(df_blk - 2, 1e-9), 3.0)
    z = float(np.sum(t_blk) / np.sqrt(np.sum(var)))
    limit = alpha / 4
    verdict.scales["mean"] = {"tests": 1, "flagged": int(2 * norm.sf(abs(z)) < limit),
                              "max_z": abs(z), "where": ("sign", 1 if z >= 0 else -1)}
    verdict.threshold_z["mean"] = float(_z_of_p(limit))
    return verdict


def comparisons(selected) -> list:
    """[(case, integrator, props)] of the cases ``selected``."""
    return [(c, k, p) for c in selected for k, p in c.integrators]


def compare_case(case, integrator, props, res, spp, seeds, alpha) -> tuple:
    """Render the comparison (seeds 0 .. K-1 for Mitsuba's, K .. 2K-1 for
    the lg integrator) and :func:`compare`: (verdict, lg images, native images)."""
    b = render_seeds(case, integrator, props, False, res, spp, range(seeds))
    a = render_seeds(case, integrator, props, True, res, spp, range(seeds, 2 * seeds))
    if a.shape != b.shape:
        raise ValueError(f"{integrator} on {case.name} returned an image of shape {a.shape}, "
                         f"Mitsuba's {b.shape}")
    return compare(a, b, alpha), a, b


# ---------------------------------------------------------------------------
#  The benchmark section
# ---------------------------------------------------------------------------

@dataclass
class ConformanceConfig:
    """The sizes of a run; ``only``: the comparisons (case, lg integrator)
    to run (None: all)."""
    res: int
    spp: int
    seeds: int
    only: tuple = None


FULL = ConformanceConfig(res=48, spp=32, seeds=12)
#: A smoke run (``lgshape bench --quick``): three comparisons, small.
QUICK = ConformanceConfig(res=16, spp=8, seeds=6,
                          only=(("hidden_sky", "lg_prb"), ("lamp_behind_null", "lg_path"),
                                ("textured", "lg_aov")))


def run(log=None, quick=False, cfg: ConformanceConfig | None = None) -> dict:
    """The conformance section: every comparison of :func:`cases`, larger
    than in the tests (``quick``: :data:`QUICK`'s three, small). Returns a
    JSON-ready dict: ``meta`` (the sizes, ALPHA) and ``records`` (one per
    comparison: the case, the integrators, per scale the tests, the
    flagged ones and the largest |z| with its limit, the seconds)."""
    import mitsuba as mi
    from .common import VARIANT
    if mi.variant() is None:
        mi.set_variant(VARIANT)
    import lgshape
    lgshape.register_plugins()
    log = log or (lambda msg: None)
    cfg = cfg or (QUICK if quick else FULL)
    todo = [(c, k, p) for c, k, p in comparisons(cases())
            if cfg.only is None or (c.name, k) in cfg.only]
    alpha = ALPHA / len(todo)
    records = []
    for case, integrator, props in todo:
        t0 = time.perf_counter()
        verdict, a, b = compare_case(case, integrator, props, cfg.res, cfg.spp, cfg.seeds, alpha)
        seconds = time.perf_counter() - t0
        shown = {k: v for k, v in props.items()}
        records.append({"case": case.name, "what": case.what, "integrator": integrator,
                        "native": NATIVE[integrator], "props": shown,
                        "scales": verdict.scales, "limits": verdict.threshold_z,
                        "flagged": verdict.flagged, "mean_lg": float(a.mean()),
                        "mean_native": float(b.mean()), "seconds": round(seconds, 2)})
        log(f"conformance {case.name} {integrator} {shown}: {verdict.flagged} flagged "
            f"({verdict.summary()}) in {seconds:.1f} s")
    return {"meta": {"res": cfg.res, "spp": cfg.spp, "seeds": cfg.seeds, "alpha": ALPHA,
                     "alpha_per_comparison": alpha, "block": BLOCK,
                     "comparisons": len(records)}, "records": records}


def report(results) -> list:
    """The markdown lines of the section."""
    meta, recs = results["meta"], results["records"]
    L = ["## Conformance against Mitsuba's integrators\n"]
    L.append(
        f"Each lg integrator against its Mitsuba counterpart on scenes whose lgsurfaces have a "
        f"native twin, {meta['res']} x {meta['res']} pixels, {meta['spp']} spp, "
        f"{meta['seeds']} independent seeds each; per comparison Welch's t per pixel and "
        f"channel, per {meta['block']} x {meta['block']} block, per channel's image mean, and "
        f"the mean of the blocks' standardized differences, at a false-alarm probability of "
        f"{meta['alpha']:g} for the whole run (Bonferroni: {meta['alpha_per_comparison']:.2g} "
        f"per comparison, a quarter per scale). A flagged test is a difference of expectation, "
        f"not noise.\n")
    L.append("| case | lg | props | flagged | max \\|z\\| pixel (limit) | block | image | "
             "mean z | lg mean | Mitsuba mean | s |")
    L.append("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in recs:
        s, lim = r["scales"], r["limits"]
        cells = [f"{s[k]['max_z']:.2f} ({lim[k]:.2f})" for k in ("pixel", "block", "image", "mean")]
        props = ", ".join(f"{k}={v}" for k, v in r["props"].items()) or "-"
        L.append(f"| {r['case']} | {r['integrator']} | {props} | {r['flagged']} | "
                 + " | ".join(cells) + f" | {r['mean_lg']:.4f} | {r['mean_native']:.4f} | "
                 f"{r['seconds']:.1f} |")
    bad = [r for r in recs if r["flagged"]]
    L.append("")
    L.append(f"{len(recs) - len(bad)} of {len(recs)} comparisons pass." +
             (" Flagged: " + ", ".join(f"{r['case']}/{r['integrator']}" for r in bad) + "."
              if bad else ""))
    L.append("")
    return L
