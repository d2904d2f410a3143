"""lg_prb's boundary term for the silhouettes of moving lgsurfaces seen
after a bounce: in a mirror, through a glass pane, in a diffuse wall's
interreflection (LGPRBIntegrator._bounce_term).

Oracle: central finite differences of lg_path's image mean (the estimator
lg_prb differentiates) in a ball's radius, h = 0.01 (the truncation error,
h^2 / 6 of the third derivative, is far below the noise), each side at the
same seed, over independent seeds; lg_prb's estimate over independent
seeds. Agreement within 4 standard errors of the difference. Where the
ball is seen only after a delta bounce (the mirror, the glass), the whole
derivative is this term's: without it (``bounce_edges`` 0) it is 0.
"""
from __future__ import annotations

import drjit as dr
import lgshape
import mitsuba as mi
import numpy as np
import pytest

from conftest import VARIANT
from gradient_oracles import central_difference, diffuse_ball as ball, forward_estimates, \
    mean_and_se

R = 0.3


@pytest.fixture(scope="module", autouse=True)
def variant():
    mi.set_variant(VARIANT)
    lgshape.register_plugins()
    yield


def scene(kind, integrator, r=R, spp=32, **props):
    """The camera at z = 4 looks at a wall at z = 0 that fills its view:
    a mirror with a black ball behind the camera (seen only in the mirror)
    and the sky; a glass slab
    (two faces) in front of a black ball and the sky; a diffuse wall lit by
    a point light, facing a lit ball behind the camera."""
    T = mi.ScalarTransform4f()
    d = {"type": "scene", "integrator": {"type": integrator, "max_depth": 3, **props},
         "sensor": {"type": "perspective", "fov": 30,
                    "to_world": T.look_at([0, 0, 4], [0, 0, 0], [0, 1, 0]),
                    "film": {"type": "hdrfilm", "width": 16, "height": 16,
                             "rfilter": {"type": "box"}},
                    "sampler": {"type": "independent", "sample_count": spp}}}
    sky = {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}}
    if kind == "mirror":
        d.update(sky=sky, mirror={"type": "rectangle", "bsdf": {"type": "conductor"},
                                  "to_world": T.scale(3)},
                 ball=ball(r, (0.3, 0.2, 5.0), 0.0))
    elif kind == "glass":
        d.update(sky=sky, pane={"type": "lgsurface", "expr": "z^2 - 0.01",
                                "bbox_min": [-3, -3, -0.2], "bbox_max": [3, 3, 0.2],
                                "to_world": T.translate([0, 0, 1.5]),
                                "bsdf": {"type": "dielectric"}},
                 ball=ball(r, (0, 0, 0), 0.0))
    else:
        d.update(wall={"type": "rectangle", "to_world": T.scale(3),
                       "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.8}}},
                 lamp={"type": "point", "position": [0, 1.5, 2.5],
                       "intensity": {"type": "rgb", "value": 20.0}},
                 ball=ball(r, (0, 0, 4.6), 0.8))
    return mi.load_dict(d)


def gradient(s, seeds):
    return mean_and_se(forward_estimates(s, "ball.r", seeds))


def difference(kind, seeds=4, h=0.01):
    return central_difference(lambda r: scene(kind, "lg_path", r, spp=256), R, h, seeds)


@pytest.mark.parametrize("kind", ["mirror", "glass", "diffuse"])
def test01_silhouette_after_a_bounce(kind):
    fd, fd_se = difference(kind)
    g, se = gradient(scene(kind, "lg_prb"), seeds=8)
    assert abs(fd) > 10 * fd_se
    assert abs(g - fd) <= 4 * (se ** 2 + fd_se ** 2) ** 0.5, (g, se, fd, fd_se)
    if kind != "diffuse":
        off, _ = gradient(scene(kind, "lg_prb", bounce_edges=0), seeds=2)
        assert off == 0.0, off


def test02_nothing_said_where_the_bounces_are_covered():
    # Oracle: LGPRBIntegrator.uncovered: max_depth 3 with bounce_edges 2
    # covers every bounce; bounce_edges 1 at max_depth 4 leaves the second.
    from lgshape.plugins import LGShapeWarning
    import warnings

    def said(s):
        params = mi.traverse(s)
        dr.enable_grad(params["ball.r"])
        params.update()
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            img = mi.render(s, params, seed=1, seed_grad=2, spp=1)
            dr.forward(params["ball.r"])
            dr.grad(img)
        return [str(w.message) for w in seen if issubclass(w.category, LGShapeWarning)
                and "after" in str(w.message)]
    assert said(scene("mirror", "lg_prb")) == []
    messages = said(scene("mirror", "lg_prb", max_depth=4, bounce_edges=1))
    assert len(messages) == 1 and "after more than 1 bounce" in messages[0], messages
