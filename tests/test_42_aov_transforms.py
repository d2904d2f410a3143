"""``lg_aov`` images and ``to_world`` transforms.

Oracles:
- AOVs: the intersection kernel itself (:meth:`lgshape.Surface.intersect`
  on an independently built Surface, rays moved to object space in float64)
  for depth, f's gradient (:meth:`lgshape.Surface.gradient`, moved to world
  space by the inverse transpose in float64) for the normals, and the floor
  plane in closed form. Camera rays are regenerated from the sensor at the
  pixel centres (a non-jittered 1-spp stratified sampler and a box filter
  put each pixel's only sample there).
- Transforms: the expression transformed by hand, f(T^-1 p), rendered with an
  identity transform; the two depth and normal images must agree.
"""
import lgshape  # noqa: F401  (before mitsuba: sets up libLLVM)
import mitsuba as mi
import numpy as np
import pytest

from lgshape import surfaces
from conftest import VARIANT

RES = 32


@pytest.fixture(autouse=True)
def variant():
    mi.set_variant(VARIANT)
    lgshape.register_plugins()


def transform():
    """A scale (non-uniform), rotation and translation."""
    return (mi.ScalarTransform4f().translate([0.2, -0.1, 0.3])
            @ mi.ScalarTransform4f().rotate([0.48, 0.6, 0.64], 35)
            @ mi.ScalarTransform4f().scale([1.4, 0.8, 1.1]))


def aov_scene(shape, aovs="dd.y:depth,nn:sh_normal,gn:geo_normal,pp:position,uv:uv"):
    return mi.load_dict({
        "type": "scene",
        "integrator": {"type": "lg_aov", "aovs": aovs},
        "sensor": {"type": "perspective", "fov": 45,
                   "to_world": mi.ScalarTransform4f().look_at([0.5, -5, 2.5], [0.2, 0, 0],
                                                              [0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": RES, "height": RES,
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "stratified", "sample_count": 1, "jitter": False}},
        "floor": {"type": "rectangle",
                  "to_world": mi.ScalarTransform4f().translate([0, 0, -1.2]).scale(5)},
        "s": shape})


def channels(scene):
    """Render; return {channel name: (RES, RES) array} (without a nested
    integrator the image holds the AOVs alone: the film's last channels)."""
    img = np.array(mi.render(scene), dtype=np.float64)
    names = [f.name for f in scene.sensors()[0].film().bitmap().struct_()]
    names = names[len(names) - img.shape[2]:]
    assert names and names[0] not in ("R", "G", "B")
    return {n: img[..., i] for i, n in enumerate(names)}


@pytest.mark.parametrize("pixel_format", ["rgb", "rgba"])
@pytest.mark.parametrize("nested", [False, True])
def test00_channels_as_mitsubas_aov(pixel_format, nested):
    # Oracle: Mitsuba's aov on the same scene of native shapes (lg_aov sees
    # them through Mitsuba's own intersection): the same channels, and the
    # same values (the same sample stream: the AOVs draw no samples).
    def scene(kind):
        integ = {"type": kind, "aovs": "dd:depth,nn:sh_normal,pp:position"}
        if nested:
            integ["image"] = {"type": "path" if kind == "aov" else "lg_path", "max_depth": 3}
        return mi.load_dict({
            "type": "scene", "integrator": integ,
            "sensor": {"type": "perspective", "fov": 40,
                       "to_world": mi.ScalarTransform4f().look_at([0, -4, 1], [0, 0, 0],
                                                                  [0, 0, 1]),
                       "film": {"type": "hdrfilm", "width": 12, "height": 10,
                                "pixel_format": pixel_format, "rfilter": {"type": "box"}},
                       "sampler": {"type": "independent", "sample_count": 4}},
            "env": {"type": "constant", "radiance": 0.5},
            "ball": {"type": "sphere", "radius": 0.8},
            "floor": {"type": "rectangle",
                      "to_world": mi.ScalarTransform4f().translate([0, 0, -1]).scale(3)}})
    ref = np.array(mi.render(scene("aov"), seed=2))
    img = np.array(mi.render(scene("lg_aov"), seed=2))
    assert img.shape == ref.shape
    # Without a nested integrator both compute the same float32 operations on
    # the same rays; with one, lg_path's rounding differs from path's by up
    # to about 100 ulp at values near 3 (an ulp there is 2.4e-7): 8e-6
    # relative.
    assert np.allclose(img, ref, rtol=1e-5, atol=1e-5)


def stack(ch, name, suffixes=".X.Y.Z"):
    return np.stack([ch[name + "." + s] for s in suffixes.split(".")[1:]], -1)


def pixel_rays(scene):
    """World-space camera rays through the pixel centres, float64 (N, 3)."""
    sensor = scene.sensors()[0]
    j, i = np.meshgrid(np.arange(RES), np.arange(RES))
    pos = mi.Point2f(((j.ravel() + 0.5) / RES).astype(np.float32),
                     ((i.ravel() + 0.5) / RES).astype(np.float32))
    ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5, 0.5))
    return np.array(ray.o, np.float64).T, np.array(ray.d, np.float64).T


def test01_aov_channels_named_like_mitsuba():
    # Oracle: Mitsuba's `aov` channel naming (3.9.1): <name>.T, .X/.Y/.Z, .U/.V;
    # the film holds R, G, B before them, the rendered image the AOVs alone.
    scene = aov_scene({"type": "lgsurface", "surface": "torus"})
    aovs = ["dd.y.T", "nn.X", "nn.Y", "nn.Z", "gn.X", "gn.Y", "gn.Z",
            "pp.X", "pp.Y", "pp.Z", "uv.U", "uv.V"]
    assert list(channels(scene)) == aovs
    assert [f.name for f in scene.sensors()[0].film().bitmap().struct_()] == ["R", "G", "B"] + aovs


def test02_aov_depth_and_normals_vs_kernel():
    # Oracle: an independent lgshape.Surface, grad f, and the floor plane.
    T = transform()
    scene = aov_scene({"type": "lgsurface", "surface": "torus", "R": 1.0, "r": 0.35, "to_world": T})
    ch = channels(scene)
    depth, gn, nn, pos = ch["dd.y.T"].ravel(), stack(ch, "gn").reshape(-1, 3), \
        stack(ch, "nn").reshape(-1, 3), stack(ch, "pp").reshape(-1, 3)

    o, d = pixel_rays(scene)
    W = np.array(T.matrix, np.float64)
    Winv = np.linalg.inv(W)
    oo, do = o @ Winv[:3, :3].T + Winv[:3, 3], d @ Winv[:3, :3].T
    surf = lgshape.Surface(surfaces.torus(1.0, 0.35))
    t, hit = surf.intersect(mi.Point3f(oo.T.astype(np.float32)),
                            mi.Vector3f(do.T.astype(np.float32)))
    t, hit = np.array(t, np.float64), np.array(hit)
    t_floor = np.where(d[:, 2] < 0, (-1.2 - o[:, 2]) / d[:, 2], np.inf)
    t_floor[np.abs(o[:, :2] + t_floor[:, None] * d[:, :2]).max(1) > 5] = np.inf
    expect = np.where(hit & (t < t_floor), t, np.where(np.isfinite(t_floor), t_floor, 0.0))
    on_torus = hit & (t < t_floor)
    assert on_torus.mean() > 0.15 and (~on_torus & (expect > 0)).mean() > 0.15

    assert np.mean(np.abs(depth - expect) < 1e-4 * np.maximum(expect, 1)) > 0.995
    seen = depth > 0
    assert np.allclose(pos[seen], (o + depth[:, None] * d)[seen], atol=1e-4)
    assert np.all(pos[~seen] == 0)

    g = np.array(surf.gradient(mi.Point3f((oo + t[:, None] * do).T.astype(np.float32))),
                 np.float64).T
    n = g @ Winv[:3, :3]                                   # inverse transpose
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    n[~on_torus] = [0, 0, 1]
    good = np.abs(depth - expect) < 1e-4 * np.maximum(expect, 1)
    assert np.abs(gn - n)[good & (expect > 0)].max() < 1e-3
    assert np.abs(nn - gn)[good].max() < 1e-6


def test03_transform_matches_hand_transformed_expression():
    # Oracle: f(T^-1 p) built by hand from the library torus, no to_world.
    T = transform()
    W = np.array(T.matrix, np.float64)
    Winv = np.linalg.inv(W)
    x, y, z = lgshape.x, lgshape.y, lgshape.z
    X, Y, Z = (Winv[i, 0] * x + Winv[i, 1] * y + Winv[i, 2] * z + Winv[i, 3] for i in range(3))
    torus = surfaces.torus(1.0, 0.35)
    R2, r2 = 1.0, 0.35 ** 2
    q = X**2 + Y**2
    by_hand = (q + Z**2 + (R2 - r2))**2 - 4 * R2 * q     # the torus formula, written out again
    lo, hi = np.array(torus.bbox)
    corners = np.array([[(hi if (k >> a) & 1 else lo)[a] for a in range(3)] for k in range(8)])
    world = corners @ W[:3, :3].T + W[:3, 3]

    a = channels(aov_scene({"type": "lgsurface", "surface": "torus", "R": 1.0, "r": 0.35,
                            "to_world": T}, "dd:depth,gn:geo_normal"))
    b = channels(aov_scene({"type": "lgsurface", "expr": str(by_hand),
                            "bbox_min": list(world.min(0)), "bbox_max": list(world.max(0))},
                           "dd:depth,gn:geo_normal"))
    da, db = a["dd.T"], b["dd.T"]
    assert (da > 0).mean() > 0.5
    assert np.mean((da > 0) == (db > 0)) > 0.995
    close = np.abs(da - db) < 1e-4 * np.maximum(da, 1)
    assert close.mean() > 0.99
    assert np.abs(stack(a, "gn") - stack(b, "gn"))[close].max() < 5e-4


def test04_nested_integrator():
    # Oracle: lg_path alone; lg_aov passes its image through unchanged (same
    # seed, same sample stream: the AOVs draw no samples).
    shape = {"type": "lgsurface", "surface": "torus"}
    base = aov_scene(shape, "dd:depth")
    path = mi.load_dict({"type": "scene", "integrator": {"type": "lg_path", "max_depth": 3},
                         "sensor": base.sensors()[0], "s": shape, "env": {"type": "constant"}})
    aov = {"type": "lg_aov", "aovs": "dd:depth", "image": {"type": "lg_path", "max_depth": 3}}
    both = mi.load_dict({"type": "scene", "integrator": aov, "sensor": base.sensors()[0],
                         "s": shape, "env": {"type": "constant"}})
    ref = np.array(mi.render(path, seed=5))
    img = np.array(mi.render(both, seed=5))
    assert img.shape[2] == ref.shape[2] + 1
    assert np.allclose(img[..., :3], ref[..., :3], atol=1e-6)
    assert (img[..., 3] > 0).mean() > 0.1


def test05_gyroid_depth_in_the_integrator():
    """The gyroid (the search on each ray's sinusoids, traced into the
    integrator's kernel) renders the depth of the direct query. Oracle:
    an independent Surface's ``intersect`` on the same rays, itself held
    against a float64 scan in test_08; and the floor plane in closed form."""
    scene = aov_scene({"type": "lgsurface", "surface": "gyroid"}, aovs="dd.y:depth")
    depth = channels(scene)["dd.y.T"].ravel()
    o, d = pixel_rays(scene)
    surf = lgshape.Surface(surfaces.gyroid())
    assert surf.ray_trig is not None
    t, hit = surf.intersect(mi.Point3f(o.T.astype(np.float32)), mi.Vector3f(d.T.astype(np.float32)))
    t, hit = np.array(t, np.float64), np.array(hit)
    t_floor = np.where(d[:, 2] < 0, (-1.2 - o[:, 2]) / d[:, 2], np.inf)
    t_floor[np.abs(o[:, :2] + t_floor[:, None] * d[:, :2]).max(1) > 5] = np.inf
    expect = np.where(hit & (t < t_floor), t, np.where(np.isfinite(t_floor), t_floor, 0.0))
    assert (hit & (t < t_floor)).mean() > 0.1
    assert np.mean(np.abs(depth - expect) < 1e-4 * np.maximum(expect, 1)) > 0.995
