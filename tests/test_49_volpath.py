"""lg_volpath: participating media with lgsurfaces.

Oracle: Mitsuba's volpath on the same scene with the lgsurface replaced by
the native shape it equals (a sphere): a homogeneous scattering interior
behind a null boundary, a glass sphere with an absorbing interior, a
heterogeneous (gridvolume) interior, and a native cube holding a medium
beside an implicit sphere. Image means over 4 seeds each (independent
estimates) agree within 4 standard errors of their difference.
"""
from __future__ import annotations

import lgshape
import mitsuba as mi
import numpy as np
import pytest

from conftest import VARIANT
from lgshape.bench.speed import fog, media_scene


@pytest.fixture(scope="module", autouse=True)
def variant():
    mi.set_variant(VARIANT)
    lgshape.register_plugins()
    yield


def ball(lg, bsdf, interior=None):
    media = {"interior": interior} if interior is not None else {}
    if lg:
        return {"type": "lgsurface", "expr": "x^2 + y^2 + z^2 - 0.36", "bbox_min": [-0.65] * 3,
                "bbox_max": [0.65] * 3, "bsdf": bsdf, **media}
    return {"type": "sphere", "radius": 0.6, "bsdf": bsdf, **media}


def scene(integrator, shapes):
    """The benchmark's media scene: ``shapes`` over a floor, 24 x 24."""
    return media_scene(shapes, integrator, 24, 64)


def absorbing():
    return {"type": "homogeneous", "sigma_t": {"type": "rgb", "value": [0.2, 0.5, 1.0]},
            "scale": 3.0, "albedo": 0.0}


def cloud():
    grid = (np.random.default_rng(0).uniform(0, 1, (8, 8, 8, 1)) ** 2).astype(np.float32)
    return {"type": "heterogeneous", "scale": 4.0,
            "sigma_t": {"type": "gridvolume", "grid": mi.VolumeGrid(grid),
                        "to_world": mi.ScalarTransform4f().translate([-0.6, -0.6, -0.6])
                        @ mi.ScalarTransform4f().scale(1.2)},
            "albedo": {"type": "rgb", "value": [0.9, 0.7, 0.5]}}


CASES = {
    "fog_in_a_null_sphere": lambda lg: {"ball": ball(lg, {"type": "null"}, fog())},
    "glass_with_absorption": lambda lg: {"ball": ball(lg, {"type": "dielectric", "int_ior": 1.5},
                                                      absorbing())},
    "heterogeneous_interior": lambda lg: {"ball": ball(lg, {"type": "null"}, cloud())},
    "native_medium_beside": lambda lg: {
        "ball": {**ball(lg, {"type": "diffuse"}),
                 "to_world": mi.ScalarTransform4f().translate([0.5, 0, 0])
                 @ mi.ScalarTransform4f().scale(0.6)},
        "box": {"type": "cube", "bsdf": {"type": "null"}, "interior": fog(),
                "to_world": mi.ScalarTransform4f().translate([-0.6, 0, 0])
                @ mi.ScalarTransform4f().scale(0.35)}},
}


def means(make, seeds=4):
    m = [float(np.mean(np.array(mi.render(make(), seed=s), np.float64))) for s in range(seeds)]
    return float(np.mean(m)), float(np.std(m, ddof=1) / np.sqrt(seeds))


@pytest.mark.parametrize("case", sorted(CASES))
def test_volpath_matches_mitsubas(case):
    a, sa = means(lambda: scene("volpath", CASES[case](False)))
    b, sb = means(lambda: scene("lg_volpath", CASES[case](True)))
    assert a > 0.05
    assert abs(a - b) <= 4 * (sa * sa + sb * sb) ** 0.5, (a, sa, b, sb)


def test_lgsurface_media_are_the_shapes():
    # Oracle: Mitsuba's Shape reads interior/exterior children of the
    # lgsurface as of any shape; and lg_volpath does not warn about media.
    s = scene("lg_volpath", CASES["fog_in_a_null_sphere"](True))
    lg = [sh for sh in s.shapes() if getattr(sh, "IS_LGSURFACE", False)][0]
    assert lg.interior_medium() is not None and lg.exterior_medium() is None
    from lgshape.plugins.checks import media_message
    assert media_message(s, s.integrator()) is None
