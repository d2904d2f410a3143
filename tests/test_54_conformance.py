"""Conformance of the lg integrators against Mitsuba's own, pixel by pixel
(:mod:`lgshape.bench.conformance`, small; ``lgshape bench`` runs every case
larger).

Oracle: Mitsuba's counterpart integrator (path, prb, direct, volpath, aov)
on the same scene with each lgsurface replaced by its native twin (sphere,
rectangle, cube, disk). Each side renders 8 independent seeds (disjoint);
per pixel and channel, per 4 x 4 block, per channel's image mean, and for
the blocks' standardized differences summed, Welch's t (Satterthwaite's
degrees of freedom) must stay below the Bonferroni limit of a false-alarm
probability of ALPHA = 1e-3 for this file's comparisons together: a failure
is a difference of expectation, not noise, whatever the machine. The cases
cover hide_emitters with a sky and with an emitting lgsurface, an emitting
lgsurface seen through a null rectangle, an emitting rectangle seen from
its back and a sphere that emits inwards, an emitting disk under
lg_direct (emitter and BSDF samples by MIS), a uv-textured sphere (and its uv
and normals through lg_aov), and the camera inside a medium.

Also: lg_prb raises lgshape's NotDifferentiableError itself for a library
parameter it cannot differentiate, and lg_volpath refuses gradient renders.
"""
from __future__ import annotations

import lgshape
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from conftest import VARIANT
from lgshape.bench import conformance as C

RES, SPP, SEEDS = 16, 16, 8

#: (case, lg integrator) of this file: the cases of conformance.cases()
#: marked quick, the integrators chosen to keep the file short.
COMPARISONS = [("hidden_sky", "lg_prb"), ("hidden_sky", "lg_path"),
               ("lamp_behind_null", "lg_path"), ("lamp_behind_null", "lg_direct"),
               ("lamp_behind_null", "lg_volpath"), ("lamp_back_sides", "lg_path"),
               ("disk_lamp", "lg_direct"), ("textured", "lg_path"), ("textured", "lg_aov"),
               ("camera_in_fog", "lg_volpath")]


@pytest.fixture(scope="module", autouse=True)
def variant():
    mi.set_variant(VARIANT)
    lgshape.register_plugins()
    yield


def _comparison(case_name, integrator):
    case = next(c for c in C.cases() if c.name == case_name)
    props = next(p for k, p in case.integrators if k == integrator)
    return case, props


@pytest.mark.parametrize("case_name, integrator", COMPARISONS,
                         ids=[f"{c}-{k}" for c, k in COMPARISONS])
def test01_matches_mitsuba_per_pixel(case_name, integrator):
    # Oracle: Mitsuba's counterpart on the native twins (module docstring).
    case, props = _comparison(case_name, integrator)
    verdict, a, b = C.compare_case(case, integrator, props, RES, SPP, SEEDS,
                                   C.ALPHA / len(COMPARISONS))
    assert b.mean() > 1e-3                             # the scene shows something
    assert verdict.flagged == 0, verdict.summary()


def test02_the_statistics_see_a_small_bias():
    # Oracle: a bias planted by hand. Two independent sets of 8 seeds of
    # the same native render pass; one of them times 1.03 (a 3% bias, below
    # the pixels' noise) fails, through the image and block scales.
    case, props = _comparison("hidden_sky", "lg_path")
    b = C.render_seeds(case, "lg_path", props, False, RES, SPP, range(SEEDS))
    a = C.render_seeds(case, "lg_path", props, False, RES, SPP, range(SEEDS, 2 * SEEDS))
    alpha = C.ALPHA / len(COMPARISONS)
    assert C.compare(a, b, alpha).flagged == 0
    biased = C.compare(a * 1.03, b, alpha)
    assert biased.flagged > 0, biased.summary()
    assert biased.scales["pixel"]["flagged"] < biased.scales["pixel"]["tests"] // 10


def gyroid_scene(integrator):
    return mi.load_dict({
        "type": "scene", "integrator": {"type": integrator, "max_depth": 2},
        "sensor": {"type": "perspective",
                   "to_world": mi.ScalarTransform4f().look_at([0, 0, 5], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 8, "height": 8},
                   "sampler": {"type": "independent", "sample_count": 2}},
        "sky": {"type": "constant"}, "g": {"type": "lgsurface", "surface": "gyroid"}})


@pytest.mark.parametrize("how", ["backward", "forward", "render_forward"])
def test03_lg_prb_raises_not_differentiable(how):
    # Oracle: the error is lgshape's NotDifferentiableError (not Dr.Jit's
    # wrapping RuntimeError) and names the parameter.
    from lgshape.plugins import NotDifferentiableError
    s = gyroid_scene("lg_prb")
    params = mi.traverse(s)
    dr.enable_grad(params["g.half_size"])
    params.update()
    message = None
    # (try/except, not pytest.raises: see test_45's test11)
    try:
        if how == "render_forward":
            s.integrator().render_forward(s, params)
        else:
            img = mi.render(s, params)
            if how == "backward":
                dr.backward(dr.mean(img, axis=None))
            else:
                dr.forward(params["g.half_size"])
    except NotDifferentiableError as err:
        message = str(err)
    dr.disable_grad(params["g.half_size"])
    assert message is not None and "'g.half_size'" in message


@pytest.mark.parametrize("how", ["backward", "forward"])
def test04_lg_volpath_refuses_gradient_renders(how):
    # Oracle: the error names the parameter and says lg_volpath computes no
    # gradients; without a gradient the same scene renders.
    from lgshape.plugins import NotDifferentiableError
    from lgshape.bench.speed import fog, media_scene
    s = media_scene({"ball": {"type": "lgsurface", "surface": "sphere", "radius": 0.6,
                              "bsdf": {"type": "null"}, "interior": fog()}}, "lg_volpath", 8, 4)
    params = mi.traverse(s)
    key = "ball.interior_medium.sigma_t.value.value"
    dr.enable_grad(params[key])
    params.update()
    message = None
    try:
        img = mi.render(s, params)
        if how == "backward":
            dr.backward(dr.mean(img, axis=None))
        else:
            dr.forward(params[key])
    except NotDifferentiableError as err:
        message = str(err)
    dr.disable_grad(params[key])
    params.update()
    assert message is not None and f"'{key}'" in message and "lg_volpath" in message
    assert "does not compute gradients" in message
    assert np.array(mi.render(s)).mean() > 0
