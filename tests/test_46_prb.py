"""lg_prb: path replay backpropagation with lgsurfaces, against finite
differences.

Oracles: lg_path's image (the primal pass, bit for bit: the same samples in
the same order); the linearity of the image in a BSDF's albedo (direct
light only: d I / d rho = I / rho exactly); central finite differences of
lg_path renders (the very estimator lg_prb differentiates) at the
differential pass's seed, so that both see the same samples.

Interior derivatives first, on scenes that move no silhouette: a bowl or
dome that fills the view under a directional light, the inside of a sphere
with a point light. Then the primary silhouettes' boundary term
(test11-13): a sphere and a torus against the sky, where the image's
derivative is mostly the silhouette's; oracle: finite differences of the
image mean, each estimate over independent seeds, within 4 standard errors
(the relaxation's remaining bias, of the order of the band's width, is
below them here: measured in docs/BENCHMARKS.md).

Tolerances (per pixel, from the arithmetic): a pixel value is a sum of spp
float32 terms of a few dozen roundings each, so two renders differ from
their exact values by at most ``ROUND * u * |I|`` (u = 2^-24, ROUND = 256
for the terms' roundings and the film's sum); a central difference with
step h then carries 2 ROUND u max|I| / (2h) of rounding, and its
truncation error (h^2 / 6 I''') is estimated by the difference against the
step 2h (which has four times the truncation error: 4/3 |FD_h - FD_2h|
bounds it, doubled); the AD value its own ROUND u |dI|.
"""
from __future__ import annotations

import lgshape
import mitsuba as mi
import numpy as np
import pytest
import drjit as dr

from conftest import VARIANT

U = 2.0 ** -24
ROUND = 256
SEED, SEED_GRAD = 3, 7


@pytest.fixture(scope="module", autouse=True)
def variant():
    mi.set_variant(VARIANT)
    lgshape.register_plugins()
    yield


def same_samples(integrator):
    """lg_prb's properties for a per-pixel oracle at the gradient seed: its
    gradient pass takes Mitsuba's camera rays (``stratified`` false), the
    samples lg_path takes at that seed, even where a boundary term is
    computed."""
    return {"stratified": False} if integrator == "lg_prb" else {}


def sensor(origin, target, fov=30, res=16, spp=16):
    return {"type": "perspective", "fov": fov,
            "to_world": mi.ScalarTransform4f().look_at(origin, target, [0, 1, 0]),
            "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}},
            "sampler": {"type": "independent", "sample_count": spp}}


def bowl_scene(integrator="lg_path", a=0.2, sign="-", shift=0.0, rho=0.5, max_depth=2):
    """z = +-a (x^2 + y^2), filling the view from above, under the sun."""
    return mi.load_dict({
        "type": "scene", "integrator": {"type": integrator, "max_depth": max_depth,
                                       **same_samples(integrator)},
        "sensor": sensor([0, 0, 3], [0, 0, 0]),
        "sun": {"type": "directional", "direction": [0.3, 0.2, -1.0],
                "irradiance": {"type": "rgb", "value": 1.0}},
        "bowl": {"type": "lgsurface", "expr": f"z {sign} a*(x^2 + y^2)", "a": a,
                 "bbox_min": [-2, -2, -1], "bbox_max": [2, 2, 1],
                 "to_world": mi.ScalarTransform4f().translate([shift, 0, 0]),
                 "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": rho}}}})


def inside_scene(integrator="lg_path", radius=1.0, max_depth=2):
    """The library sphere seen from inside (a two-sided wall), lit by a
    point light inside it: the whole view is the wall."""
    return mi.load_dict({
        "type": "scene", "integrator": {"type": integrator, "max_depth": max_depth,
                                       **same_samples(integrator)},
        "sensor": sensor([0.1, 0, 0], [0.1, 0, -1], fov=60),
        "lamp": {"type": "point", "position": [0, 0.3, 0.2],
                 "intensity": {"type": "rgb", "value": 1.0}},
        "wall": {"type": "lgsurface", "surface": "sphere", "radius": radius,
                 "bsdf": {"type": "twosided", "bsdf": {
                     "type": "diffuse", "reflectance": {"type": "rgb", "value": 0.6}}}}})


def render(scene, seed=SEED):
    return np.array(mi.render(scene, seed=seed), np.float64)


def ad_forward(scene, key):
    params = mi.traverse(scene)
    dr.enable_grad(params[key])
    params.update()
    img = mi.render(scene, params, seed=SEED, seed_grad=SEED_GRAD)
    dr.forward(params[key])
    return np.array(dr.grad(img), np.float64)


def ad_backward(scene, key, weights):
    params = mi.traverse(scene)
    dr.enable_grad(params[key])
    params.update()
    img = mi.render(scene, params, seed=SEED, seed_grad=SEED_GRAD)
    dr.backward(dr.sum(img * mi.TensorXf(np.float32(weights)), axis=None))
    return float(dr.grad(params[key])[0])


def finite_difference(make, value, h):
    """(FD_h, its error bound) of the renders make(v) at the gradient seed."""
    def fd(step):
        return (render(make(value + step), SEED_GRAD) - render(make(value - step), SEED_GRAD)) \
            / (2 * step)
    f1, f2 = fd(h), fd(2 * h)
    peak = np.abs(render(make(value), SEED_GRAD)).max()
    bound = 2 * ROUND * U * peak / (2 * h) + 2 * (4 / 3) * np.abs(f1 - f2)
    return f1, bound


def check(g, fd, bound, what):
    tol = bound + ROUND * U * np.abs(g)
    bad = np.abs(g - fd) > tol
    assert not bad.any(), (f"{what}: {int(bad.sum())} pixels off; worst |AD - FD| "
                           f"{np.abs(g - fd).max():.3g}, tolerance there "
                           f"{tol.flat[np.argmax(np.abs(g - fd))]:.3g}")


def test01_primal_is_lg_paths_image():
    # Oracle: lg_path on the same scene and seed (same samples, same order),
    # with paths of several bounces and Russian roulette; the contributions
    # are summed in another order (up to ROUND u of the pixel).
    for make in (lambda i: bowl_scene(i, max_depth=6), lambda i: inside_scene(i, max_depth=8)):
        a, b = render(make("lg_path")), render(make("lg_prb"))
        assert a.max() > 0
        assert np.all(np.abs(a - b) <= ROUND * U * np.abs(a))


def test02_albedo_gradient_is_the_image_over_albedo():
    # Oracle: direct light only (max_depth 2), the image is linear in the
    # surface's albedo rho: dI / drho = I / rho, at the gradient seed.
    s = bowl_scene("lg_prb")
    g = ad_forward(s, "bowl.bsdf.reflectance.value")
    expected = render(bowl_scene("lg_path"), SEED_GRAD) / 0.5
    assert np.abs(g - expected).max() <= ROUND * U * np.abs(expected).max() * 4


@pytest.mark.parametrize("sign", ["-", "+"])
def test03_shape_parameter_seen_through_shading(sign):
    # Oracle: central differences of lg_path renders (bowl and dome, the
    # curvature a changes every normal and hit point; no silhouette).
    g = ad_forward(bowl_scene("lg_prb", sign=sign), "bowl.a")
    fd, bound = finite_difference(lambda a: bowl_scene(a=a, sign=sign), 0.2, 1e-2)
    assert np.abs(fd).max() > 0.01
    check(g, fd, bound, f"z {sign} a r^2, d/da")


def test04_backward_equals_forward():
    # Oracle: the same derivative two ways: the forward image weighted by
    # w, summed, against the backward pass of the weighted sum.
    s = bowl_scene("lg_prb")
    g = ad_forward(s, "bowl.a")
    w = np.random.default_rng(2).uniform(0, 1, g.shape)
    gb = ad_backward(bowl_scene("lg_prb"), "bowl.a", w)
    assert abs(gb - float((g * w).sum())) <= ROUND * U * float(np.abs(g * w).sum()) * 4


def test05_translation_in_to_world():
    # Oracle: central differences in the translation x of to_world.
    s = bowl_scene("lg_prb")
    params = mi.traverse(s)
    x = mi.Float(0.0)
    dr.enable_grad(x)
    params["bowl.to_world"] = mi.Transform4f().translate(mi.Vector3f(x, 0, 0))
    params.update()
    img = mi.render(s, params, seed=SEED, seed_grad=SEED_GRAD)
    dr.forward(x)
    g = np.array(dr.grad(img), np.float64)
    fd, bound = finite_difference(lambda v: bowl_scene(shift=v), 0.0, 1e-2)
    assert np.abs(fd).max() > 0.01
    check(g, fd, bound, "to_world translate x")


def test06_library_surface_parameter():
    # Oracle: central differences in the library sphere's radius, seen from
    # inside (the wall moves away from the lamp and the camera).
    g = ad_forward(inside_scene("lg_prb"), "wall.radius")
    fd, bound = finite_difference(lambda r: inside_scene(radius=r), 1.0, 1e-2)
    assert np.abs(fd).max() > 0.01
    check(g, fd, bound, "sphere radius, inside")


def test07_other_integrators_refuse_surface_gradients():
    # Oracle: the error names the parameter and lg_prb.
    s = bowl_scene("lg_path")
    params = mi.traverse(s)
    dr.enable_grad(params["bowl.a"])
    params.update()
    from lgshape.plugins import NotDifferentiableError
    # (try/except, not pytest.raises: see test_45's test11)
    try:
        mi.render(s, params)
        message = None
    except NotDifferentiableError as err:
        message = str(err)
    dr.disable_grad(params["bowl.a"])
    assert message is not None and "'bowl.a'" in message and "lg_prb" in message


def test08_parameters_are_differentiable_floats():
    # Oracle: mi.traverse's flags (Mitsuba's convention: geometry
    # parameters are Differentiable | Discontinuous).
    params = mi.traverse(bowl_scene("lg_prb"))
    for key in ("bowl.a", "bowl.to_world"):
        assert params.flags(key) & int(mi.ParamFlags.Discontinuous)
        assert not params.flags(key) & int(mi.ParamFlags.NonDifferentiable)
    assert isinstance(params["bowl.a"], mi.Float)


def cube_scene(integrator, wall, max_depth):
    return mi.load_dict({
        "type": "scene", "integrator": {"type": integrator, "max_depth": max_depth,
                                       **same_samples(integrator)},
        "sensor": sensor([0.1, 0, 0], [0.1, 0, -1], fov=60),
        "lamp": {"type": "point", "position": [0, 0.3, 0.2],
                 "intensity": {"type": "rgb", "value": 1.0}},
        "wall": dict(wall, bsdf={"type": "twosided", "bsdf": {
            "type": "diffuse", "reflectance": {"type": "rgb", "value": 0.6}}})})


def scaled_cube_gradient(scene):
    """d image / d x for the mesh cube's vertices scaled by x (about 0)."""
    params = mi.traverse(scene)
    v0 = dr.unravel(mi.Point3f, params["wall.vertex_positions"])
    x = mi.Float(1.0)
    dr.enable_grad(x)
    params["wall.vertex_positions"] = dr.ravel(v0 * x)
    params.update()
    img = mi.render(scene, params, seed=SEED, seed_grad=SEED_GRAD)
    dr.forward(x)
    return np.array(dr.grad(img), np.float64)


def test09_native_scene_is_mitsubas_prb():
    # Oracle: Mitsuba's prb on a scene of native shapes only (an inside
    # view of a mesh cube that grows, indirect light included): lg_prb's
    # replay is prb's, the same gradient image to rounding.
    g_prb = scaled_cube_gradient(cube_scene("prb", {"type": "cube"}, 4))
    g_lg = scaled_cube_gradient(cube_scene("lg_prb", {"type": "cube"}, 4))
    assert np.abs(g_prb).max() > 0.01
    assert np.all(np.abs(g_prb - g_lg) <= ROUND * U * (np.abs(g_prb) + np.abs(g_prb).max()))


def test10_implicit_cube_is_the_mesh_cube():
    # Oracle: Mitsuba's prb on the mesh cube scaled by x, against lg_prb on
    # the implicit cube max(|x|, |y|, |z|) = s, d/ds at s = 1: the same
    # surface moving the same way (direct light: the same samples).
    g_mesh = scaled_cube_gradient(cube_scene("prb", {"type": "cube"}, 2))
    implicit = {"type": "lgsurface", "expr": "max(abs(x), max(abs(y), abs(z))) - s", "s": 1.0,
                "bbox_min": [-1.1] * 3, "bbox_max": [1.1] * 3}
    g_lg = ad_forward(cube_scene("lg_prb", implicit, 2), "wall.s")
    assert np.abs(g_mesh).max() > 0.01
    assert np.all(np.abs(g_mesh - g_lg) <= ROUND * U * (np.abs(g_mesh) + np.abs(g_mesh).max()))


def sky_scene(integrator, shape, spp=64, **integrator_props):
    """A shape against a uniform sky under the sun, direct light only."""
    return mi.load_dict({
        "type": "scene", "integrator": {"type": integrator, "max_depth": 2, **integrator_props},
        "sensor": {**sensor([0, 0, 4], [0, 0, 0], res=32, spp=spp)},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 0.2}},
        "sun": {"type": "directional", "direction": [0.3, 0.2, -1.0],
                "irradiance": {"type": "rgb", "value": 2.0}},
        "obj": {**shape, "bsdf": {"type": "diffuse",
                                  "reflectance": {"type": "rgb", "value": 0.8}}}})


def ball(r):
    return {"type": "lgsurface", "expr": "x^2 + y^2 + z^2 - r^2", "r": r,
            "bbox_min": [-1, -1, -1], "bbox_max": [1, 1, 1]}


def torus(r):
    return {"type": "lgsurface", "surface": "torus", "R": 0.7, "r": r,
            "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], 60)}


def mean_gradient(make, key, seeds=4, **props):
    """d mean(image) / d key by lg_prb, over independent seeds: (mean, SE)."""
    out = []
    for k in range(seeds):
        s = make("lg_prb", **props)
        params = mi.traverse(s)
        dr.enable_grad(params[key])
        params.update()
        img = mi.render(s, params, seed=2 * k + 100, seed_grad=2 * k + 101)
        dr.forward(params[key])
        out.append(float(np.mean(np.array(dr.grad(img), np.float64))))
    return float(np.mean(out)), float(np.std(out, ddof=1) / np.sqrt(seeds)) if seeds > 1 else 0.0


def mean_difference(make, value, h, seeds=4):
    """The central difference of mean(image) over independent seeds, 4x
    the spp: (mean, SE)."""
    out = []
    for k in range(seeds):
        a = np.mean(np.array(mi.render(make(value + h), seed=k, spp=256), np.float64))
        b = np.mean(np.array(mi.render(make(value - h), seed=k, spp=256), np.float64))
        out.append((a - b) / (2 * h))
    return float(np.mean(out)), float(np.std(out, ddof=1) / np.sqrt(seeds))


@pytest.mark.parametrize("shape, key, value", [(ball, "obj.r", 0.6), (torus, "obj.r", 0.25)],
                         ids=["sphere radius", "torus tube radius"])
def test11_silhouette_gradient(shape, key, value):
    # Oracle: central differences of lg_path's image mean (h = 1e-2: the
    # truncation error, h^2 / 6 of the third derivative, is far below the
    # noise); the interior term alone misses the silhouette's share.
    def make(integrator, v=value, **props):
        return sky_scene(integrator, shape(v), **props)
    fd, fd_se = mean_difference(lambda v: make("lg_path", v), value, 1e-2)
    g, g_se = mean_gradient(make, key)
    interior, i_se = mean_gradient(make, key, boundary=False)
    sigma = (fd_se ** 2 + g_se ** 2) ** 0.5
    assert abs(g - fd) <= 4 * sigma, (g, g_se, fd, fd_se)
    assert abs(interior - fd) > 4 * (fd_se ** 2 + i_se ** 2) ** 0.5     # the term matters


def test12_flat_silhouette_is_the_disc_area():
    # Oracle: a black sphere (radius r, at distance D) against a sky of
    # radiance 0.2: the image mean is 0.2 (1 - coverage), coverage = the
    # disc pi tan^2(a) / (2 tan 15 deg)^2 with tan a = r / sqrt(D^2 - r^2),
    # differentiated in closed form; the whole derivative is the boundary's.
    r, D, half = 0.6, 4.0, np.tan(np.radians(15))

    shape_black = {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.0}}

    def black(integrator, v=r, **props):
        return mi.load_dict({
            "type": "scene", "integrator": {"type": integrator, "max_depth": 2, **props},
            "sensor": sensor([0, 0, D], [0, 0, 0], res=32, spp=64),
            "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 0.2}},
            "obj": {**ball(v), "bsdf": shape_black}})
    tan_a = r / np.sqrt(D * D - r * r)
    dtan = D * D / (D * D - r * r) ** 1.5
    expected = -0.2 * np.pi * 2 * tan_a * dtan / (2 * half) ** 2
    g, g_se = mean_gradient(black, "obj.r")
    assert abs(g - expected) <= 4 * g_se, (g, g_se, expected)


def test13_backward_silhouette_equals_forward():
    # Oracle: the same estimate two ways (same seeds): dr.backward of the
    # image mean against the mean of the forward gradient image.
    def make(integrator, **props):
        return sky_scene(integrator, ball(0.6), **props)
    g, _ = mean_gradient(make, "obj.r", seeds=1)
    s = make("lg_prb")
    params = mi.traverse(s)
    dr.enable_grad(params["obj.r"])
    params.update()
    img = mi.render(s, params, seed=100, seed_grad=101)
    dr.backward(dr.mean(img, axis=None))
    gb = float(dr.grad(params["obj.r"])[0])
    assert abs(gb - g) <= ROUND * U * 64 * abs(g) + 1e-6


def test14_blend_threshold(tmp_path):
    # Oracle: central differences of the image mean in a primitives file's
    # blend threshold (three blobs; the iso-level moves every silhouette).
    path = tmp_path / "blobs.txt"
    path.write_text("sphere -0.35 0 0 0.5\nsphere 0.35 0 0 0.5\nsphere 0 0.35 0.1 0.45\n")

    def make(integrator, v=0.5, **props):
        return sky_scene(integrator, {"type": "lgsurface", "primitives": str(path),
                                      "combine": "blend", "threshold": v}, **props)
    fd, fd_se = mean_difference(lambda v: make("lg_path", v), 0.5, 1e-2)
    g, g_se = mean_gradient(make, "obj.threshold")
    assert abs(fd) > 10 * fd_se
    assert abs(g - fd) <= 4 * (fd_se ** 2 + g_se ** 2) ** 0.5, (g, g_se, fd, fd_se)


@pytest.mark.parametrize("D", [6, 12, 40])
def test15_long_paths_inside_an_emitting_sphere(D):
    # Oracle: the furnace in closed form. Seen from inside, a sphere that
    # emits Le and reflects rho (diffuse) everywhere: every vertex of every
    # path lies on it, and a path of max_depth D brings Le sum_{k<D} rho^k
    # whatever its directions, so the image is that and its derivative in
    # rho is Le sum_k k rho^(k-1). No Russian roulette. The three depths
    # cover the replay's three regimes (lg_prb.PathRecord): D = 6, the
    # record holds every hit and shadow test; D = 12, the replay searches
    # after the 8 hits it holds; D = 40, it also tests shadows after vertex
    # 32. Another lgsurface before the sphere in the scene, never hit, makes
    # the sphere's index 2. Each pixel's estimate is noisy only through the
    # emitter sampling's MIS (BSDF and cone samples of the same uniform
    # emission): the mean over pixels within 4 standard errors.
    rho, Le = 0.8, 1.0
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "lg_prb", "max_depth": D, "rr_depth": 1000},
        "sensor": sensor([0, 0, 0], [0, 0, -1], fov=60, res=16, spp=16),
        "far": {"type": "lgsurface", "surface": "sphere", "radius": 0.1,
                "to_world": mi.ScalarTransform4f().translate([0, 0, 10])},
        "wall": {"type": "lgsurface", "surface": "sphere", "radius": 1.0,
                 "flip_normals": True,
                 "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": rho}},
                 "emitter": {"type": "area", "radiance": {"type": "rgb", "value": Le}}}})
    k = np.arange(D)
    image = Le * np.sum(rho ** k)
    slope = Le * np.sum(k[1:] * rho ** (k[1:] - 1))
    for got, expected in ((render(scene), image),
                          (ad_forward(scene, "wall.bsdf.reflectance.value"), slope)):
        se = got.std() / np.sqrt(got.size)
        assert abs(got.mean() - expected) <= 4 * se + ROUND * U * expected, \
            (got.mean(), se, expected)


def test16_hidden_emitters():
    # Oracle: the image's linearity in the floor's albedo rho (direct light
    # only, max_depth 2): dI / drho = I / rho, at the gradient seed, with an
    # emitting lgsurface hidden from the camera (hide_emitters: the camera
    # rays that hit it continue to the floor behind, in the primal pass and,
    # handed over by it, in the replay).
    from lgshape.bench.speed import emitter_scene
    lamp = {"type": "lgsurface", "surface": "sphere", "radius": 0.3,
            "to_world": mi.ScalarTransform4f().translate([0, 0.4, 0])}

    def make(integrator):
        return emitter_scene(lamp, integrator, res=16, spp=16, max_depth=2, hide_emitters=True)
    g = ad_forward(make("lg_prb"), "floor.bsdf.reflectance.value")
    expected = render(make("lg_path"), SEED_GRAD) / 0.6
    assert expected.max() > 0
    assert np.abs(g - expected).max() <= ROUND * U * np.abs(expected).max() * 4


def shadow_scene(integrator, r=0.25, spp=64, **integrator_props):
    """A ball above a floor under a point light, out of the camera's view:
    the image sees the ball only through its shadow."""
    return mi.load_dict({
        "type": "scene", "integrator": {"type": integrator, "max_depth": 2, **integrator_props},
        "sensor": sensor([0, 0.4, 1.5], [0, 0, 0], fov=25, res=32, spp=spp),
        "lamp": {"type": "point", "position": [0.3, 2.0, 0.0],
                 "intensity": {"type": "rgb", "value": 4.0}},
        "floor": {"type": "rectangle",
                  "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90)
                  @ mi.ScalarTransform4f().scale(2),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.8}}},
        "obj": {**ball(r), "to_world": mi.ScalarTransform4f().translate([0, 0.8, 0]),
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.5}}}})


def test17_shadow_edge_gradient():
    # Oracle: central differences of lg_path's image mean in the radius of
    # a ball that the camera sees only through its shadow: the whole
    # derivative is the shadow edge's (without that term it is 0). Within
    # 4 standard errors of the two estimates.
    make = shadow_scene
    fd, fd_se = mean_difference(lambda v: make("lg_path", v), 0.25, 1e-2)
    g, g_se = mean_gradient(make, "obj.r")
    off, _ = mean_gradient(make, "obj.r", seeds=1, shadow_edges=False)
    assert abs(fd) > 10 * fd_se and off == 0.0
    assert abs(g - fd) <= 4 * (fd_se ** 2 + g_se ** 2) ** 0.5, (g, g_se, fd, fd_se)


def test18_orthographic_silhouette_is_the_disc_area():
    # Oracle: as test12 through an orthographic camera that sees a 2s x 2s
    # window: the mean is 0.2 (1 - pi r^2 / (2s)^2), so d/dr = -0.2 2 pi r /
    # (2s)^2 in closed form (the band's width comes from the pixels' spread
    # of origins, not of directions).
    r, s = 0.6, 1.2

    def black(integrator, v=r, **props):
        return mi.load_dict({
            "type": "scene", "integrator": {"type": integrator, "max_depth": 2, **props},
            "sensor": {"type": "orthographic",
                       "to_world": mi.ScalarTransform4f().look_at([0, 0, 4], [0, 0, 0], [0, 1, 0])
                       @ mi.ScalarTransform4f().scale([s, s, 1]),
                       "film": {"type": "hdrfilm", "width": 32, "height": 32,
                                "rfilter": {"type": "box"}},
                       "sampler": {"type": "independent", "sample_count": 64}},
            "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 0.2}},
            "obj": {**ball(v), "bsdf": {"type": "diffuse",
                                        "reflectance": {"type": "rgb", "value": 0.0}}}})
    expected = -0.2 * 2 * np.pi * r / (2 * s) ** 2
    g, g_se = mean_gradient(black, "obj.r")
    assert abs(g - expected) <= 4 * g_se, (g, g_se, expected)
