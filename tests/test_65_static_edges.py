"""lg_prb's boundary terms for the edges of *static* lgsurfaces as seen from
a moving one: the shadow a static lgsurface casts on a moving lgsurface
moves across it as its surface moves (LGPRBIntegrator._shadow_edge, whose
occluders are every lgsurface where the shadow ray's ends move).

Oracle: central finite differences of lg_path's image mean (the estimator
lg_prb differentiates) in the moving ball's radius, h = 0.01 (the
truncation error, h^2 / 6 of the third derivative, is far below the noise),
each side at the same seed, over independent seeds; lg_prb's estimate
(forward mode) over independent seeds. Agreement within 4 standard errors
of the difference. Without the shadow-edge term (``shadow_edges`` off) the
estimate misses the static occluder's moving shadow: the difference
between the two is the term, and it must be several of its standard errors
from 0.
"""
from __future__ import annotations

import drjit as dr
import lgshape
import mitsuba as mi
import numpy as np
import pytest

from conftest import VARIANT
from gradient_oracles import central_difference, diffuse_ball, forward_estimates

R = 0.5


@pytest.fixture(scope="module", autouse=True)
def variant():
    mi.set_variant(VARIANT)
    lgshape.register_plugins()
    yield


def ball(r, at, rho):
    return diffuse_ball(r, at, rho, half=0.7)


def scene(integrator, r=R, spp=32, **props):
    """A white ball of radius r (the moving one) under a point light, and a
    small black static ball between them whose shadow falls on its top;
    no background."""
    T = mi.ScalarTransform4f()
    return mi.load_dict({
        "type": "scene", "integrator": {"type": integrator, "max_depth": 3, **props},
        "sensor": {"type": "perspective", "fov": 30,
                   "to_world": T.look_at([0, -4, 0.6], [0, 0, 0.2], [0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": 32, "height": 32,
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "obj": ball(r, (0, 0, 0), 0.8),
        "occ": ball(0.12, (0.0, -0.1, 0.95), 0.0),
        "lamp": {"type": "point", "position": [0, -0.3, 2.4],
                 "intensity": {"type": "rgb", "value": 8.0}}})


def gradients(s, seeds):
    return forward_estimates(s, "obj.r", seeds)


def difference(seeds=4, h=0.01):
    return central_difference(lambda r: scene("lg_path", r, spp=256), R, h, seeds)


def test01_static_occluders_shadow_on_a_moving_surface():
    fd, fd_se = difference()
    on = gradients(scene("lg_prb"), seeds=8)
    off = gradients(scene("lg_prb", shadow_edges=False), seeds=8)
    g, se = on.mean(), on.std(ddof=1) / np.sqrt(len(on))
    assert abs(fd) > 10 * fd_se
    assert abs(g - fd) <= 4 * np.hypot(se, fd_se), (g, se, fd, fd_se)
    # the term (the same seeds: the two estimates share their other terms)
    term = on - off
    term_se = term.std(ddof=1) / np.sqrt(len(term))
    assert term.mean() > 4 * term_se, (term.mean(), term_se)


def test02_a_moving_mirror_is_said_to_be_left_out():
    # Oracle: measured against finite differences (a mirror ball filling
    # the view, reflecting a lit floor, d mean / d r: FD -0.0552, lg_prb
    # +0.0099): the replay moves each vertex with its own surface, and the
    # turn of the reflected direction is not followed. uncovered() says so
    # for a moving lgsurface whose BSDF has a delta lobe, whether or not
    # boundary terms are on; a diffuse one is not named.
    for boundary in (True, False):
        s = scene("lg_prb", boundary=boundary)
        params = mi.traverse(s)
        dr.enable_grad(params["obj.r"])
        params.update()
        assert not [m for m in s.integrator().uncovered(s) if "delta BSDF" in m]
    T = mi.ScalarTransform4f()
    s = mi.load_dict({"type": "scene", "integrator": {"type": "lg_prb", "max_depth": 3},
                      "obj": {**ball(R, (0, 0, 0), 0.5), "bsdf": {"type": "conductor"}},
                      "sensor": {"type": "perspective",
                                 "to_world": T.look_at([0, -4, 0], [0, 0, 0], [0, 0, 1])}})
    params = mi.traverse(s)
    dr.enable_grad(params["obj.r"])
    params.update()
    said = [m for m in s.integrator().uncovered(s) if "delta BSDF" in m]
    assert len(said) == 1 and "'obj'" in said[0], said
