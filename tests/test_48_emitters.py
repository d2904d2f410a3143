"""Area emitters on lgsurfaces: emission where a path hits the surface and
next-event estimation that samples it (the traced cone of its bounding
sphere, an exact density), combined with BSDF sampling by MIS, in lg_path,
lg_direct, lg_volpath and lg_prb; uniform and textured radiance.

Oracles: Mitsuba's own integrators on the same scene with the native
emitting sphere (its visible-cap sampling); for a torus emitter (non-convex:
cone directions through its hole miss it), lg_direct with BSDF samples
only; for a texture's gradient, Euler's theorem (the image is linear in
the texels). Image means over 4 seeds each (independent estimates) agree within 4
standard errors of their difference.
"""
from __future__ import annotations

import lgshape
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from conftest import VARIANT
from lgshape.bench.speed import emitter_scene


@pytest.fixture(scope="module", autouse=True)
def variant():
    mi.set_variant(VARIANT)
    lgshape.register_plugins()
    yield


def scene(integrator, emitter_shape, spp=64, **props):
    """The benchmark's emitter scene (a lamp over a floor), 32 x 32."""
    return emitter_scene(emitter_shape, integrator, 32, spp, **props)


def lg_ball():
    return {"type": "lgsurface", "expr": "x^2 + y^2 + z^2 - 0.09", "bbox_min": [-0.35] * 3,
            "bbox_max": [0.35] * 3, "to_world": mi.ScalarTransform4f().translate([0, 0.4, 0])}


BALL = {"type": "sphere", "radius": 0.3, "center": [0, 0.4, 0]}


def means(make, seeds=4):
    m = [float(np.mean(np.array(mi.render(make(), seed=s), np.float64))) for s in range(seeds)]
    return float(np.mean(m)), float(np.std(m, ddof=1) / np.sqrt(seeds))


@pytest.mark.parametrize("lg, native, props", [
    ("lg_path", "path", {"max_depth": 3}), ("lg_direct", "direct", {}),
    ("lg_prb", "path", {"max_depth": 3})], ids=["lg_path", "lg_direct", "lg_prb"])
def test01_emitting_sphere_matches_mitsubas(lg, native, props):
    # Oracle: Mitsuba's integrator with the native emitting sphere.
    a, sa = means(lambda: scene(native, BALL, **props))
    b, sb = means(lambda: scene(lg, lg_ball(), **props))
    assert a > 0.1
    assert abs(a - b) <= 4 * (sa * sa + sb * sb) ** 0.5, (a, sa, b, sb)


def test02_emitter_in_the_scene_list():
    # Oracle: Mitsuba's scene.emitters() holds the area emitter of the
    # lgsurface, and the shape's emitter() is it.
    s = scene("lg_path", lg_ball())
    lamp = [sh for sh in s.shapes() if getattr(sh, "IS_LGSURFACE", False)][0]
    assert lamp.emitter() is not None
    assert any(e.ptr == lamp.emitter().ptr for e in s.emitters())
    # and mi.traverse lists the emitter's parameters under the shape's id
    assert "lamp.emitter.radiance.value" in mi.traverse(s).keys()


def test03_non_convex_emitter_against_bsdf_sampling():
    # Oracle: a torus emitter lighting the floor, direct light: lg_direct
    # with emitter and BSDF samples (MIS) against lg_direct with BSDF
    # samples only (the emitter reached by BSDF sampling alone), 4x as many.
    torus = {"type": "lgsurface", "surface": "torus", "R": 0.35, "r": 0.1,
             "to_world": mi.ScalarTransform4f().translate([0, 0.4, 0])
             @ mi.ScalarTransform4f().rotate([1, 0, 0], 70)}
    a, sa = means(lambda: scene("lg_direct", torus))
    b, sb = means(lambda: scene("lg_direct", torus, emitter_samples=0, bsdf_samples=4))
    assert a > 0.02
    assert abs(a - b) <= 4 * (sa * sa + sb * sb) ** 0.5, (a, sa, b, sb)


def bitmap_radiance():
    """A raw 8 x 4 bitmap of radiance 0.5 to 6, nearest texel: every texel
    a patch of the surface's uv (Mitsuba's sphere's convention)."""
    texels = np.random.default_rng(3).uniform(0.5, 6.0, (4, 8, 3)).astype(np.float32)
    return {"type": "bitmap", "bitmap": mi.Bitmap(texels), "raw": True, "filter_type": "nearest"}


@pytest.mark.parametrize("lg, native, props", [
    ("lg_path", "path", {"max_depth": 1}), ("lg_path", "path", {"max_depth": 3}),
    ("lg_direct", "direct", {}), ("lg_volpath", "volpath", {"max_depth": 3}),
    ("lg_prb", "path", {"max_depth": 3})],
    ids=["lg_path_seen", "lg_path", "lg_direct", "lg_volpath", "lg_prb"])
def test05_textured_radiance_matches_mitsubas(lg, native, props):
    # Oracle: Mitsuba's integrator with the native emitting sphere and the
    # same texture (the lgsurface's uv is Mitsuba's sphere's: u the azimuth,
    # v the polar angle about the centre). max_depth 1: the emitter seen
    # directly (its texture at the hits' uv); otherwise the floor it lights,
    # by next-event estimation at the sampled points' uv, and MIS.
    tex = bitmap_radiance()
    a, sa = means(lambda: scene(native, BALL, radiance=tex, **props))
    b, sb = means(lambda: scene(lg, lg_ball(), radiance=tex, **props))
    assert a > 0.1
    assert abs(a - b) <= 4 * (sa * sa + sb * sb) ** 0.5, (a, sa, b, sb)


def test06_textured_radiance_gradient():
    # Oracle: the emitter is the only light, so the image is linear in the
    # texels x_i and sum_i x_i dI/dx_i = I (Euler's theorem): lg_prb's
    # gradient of the image mean, dotted with the texels, against the image
    # mean, each over 4 seeds (independent estimates).
    s = scene("lg_prb", lg_ball(), radiance=bitmap_radiance(), max_depth=3)
    params = mi.traverse(s)
    key = "lamp.emitter.radiance.data"
    texels = np.array(params[key], np.float64)
    euler = []
    for seed in range(4):
        dr.enable_grad(params[key])
        params.update()
        dr.backward(dr.mean(mi.render(s, params, seed=seed, seed_grad=10 + seed), axis=None))
        euler.append(float(np.sum(np.array(dr.grad(params[key]), np.float64) * texels)))
        dr.disable_grad(params[key])
        params.update()
    a, sa = float(np.mean(euler)), float(np.std(euler, ddof=1) / 2)
    b, sb = means(lambda: scene("lg_path", lg_ball(), radiance=bitmap_radiance(),
                                max_depth=3))
    assert a > 0.1
    assert abs(a - b) <= 4 * (sa * sa + sb * sb) ** 0.5, (a, sa, b, sb)


def test04_other_emitters_refused():
    # Oracle: the message names the child and says only 'area' fits.
    try:
        mi.load_dict({"type": "scene", "lamp": {**lg_ball(), "light": {"type": "point"}}})
        message = None
    except Exception as err:              # (Mitsuba wraps the plugin's ValueError)
        message = str(err)
    assert message is not None and "only an 'area' emitter" in message


def test07_sampling_weight_respected():
    # Oracle: Mitsuba's emitter choice, pdf_emitter = w / sum of weights
    # (here the lgsurface's emitter against a constant sky of weight 1), and
    # unbiasedness: the image mean does not depend on the weights (means of
    # 4 seeds at weights 4 and 0.25 agree within 4 standard errors).
    def make(weight):
        return mi.load_dict({
            "type": "scene", "integrator": {"type": "lg_path", "max_depth": 3},
            "sensor": {"type": "perspective", "fov": 45,
                       "to_world": mi.ScalarTransform4f().look_at([0, 0.5, 3], [0, 0, 0],
                                                                  [0, 1, 0]),
                       "film": {"type": "hdrfilm", "width": 32, "height": 32,
                                "rfilter": {"type": "box"}},
                       "sampler": {"type": "independent", "sample_count": 64}},
            "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 0.2}},
            "floor": {"type": "rectangle",
                      "to_world": mi.ScalarTransform4f().translate([0, -0.3, 0])
                      @ mi.ScalarTransform4f().rotate([1, 0, 0], -90)},
            "lamp": {**lg_ball(), "emitter": {"type": "area", "sampling_weight": weight,
                                              "radiance": {"type": "rgb", "value": 4.0}}}})
    s = make(4.0)
    lamp = [sh for sh in s.shapes() if getattr(sh, "IS_LGSURFACE", False)][0]
    assert lamp.emitter().sampling_weight() == 4.0
    index = next(i for i, e in enumerate(s.emitters()) if e.ptr == lamp.emitter().ptr)
    assert abs(float(s.pdf_emitter(index)[0]) - 0.8) <= 1e-6
    a, sa = means(lambda: make(4.0))
    b, sb = means(lambda: make(0.25))
    assert a > 0.1
    assert abs(a - b) <= 4 * (sa * sa + sb * sb) ** 0.5, (a, sa, b, sb)
