"""lg_prb's replay of a moving mirror or glass lgsurface: the reflected and
refracted directions turn with its normal along the camera's delta vertices
(LGPRBIntegrator._chain_ray), and what is seen in it or through it moves
with them.

Scenes without silhouettes, so that the derivative is the interior term
alone: the camera looks down at a surface that fills its view, which shows
a smooth environment map (no edges). A mirror plane z = c y tilts with c
(one delta vertex); a glass slab whose top face tilts with c, a prism
(two refractions, and internal reflections).

Oracle: central finite differences of lg_path's image mean in c, h = 0.01,
each side at the same seed, over independent seeds (the truncation error,
h^2 / 6 of the third derivative, is far below the noise); lg_prb's forward
estimates over independent seeds; agreement within 4 standard errors of
the difference. Before the chain was followed, lg_prb gave -0.009 for the
mirror (finite differences: 0.204) and -1.63 for the prism (-0.079).
"""
from __future__ import annotations

import mitsuba as mi
import numpy as np
import pytest

import lgshape
from conftest import VARIANT
from gradient_oracles import central_difference, forward_estimates, mean_and_se


@pytest.fixture(scope="module", autouse=True)
def variant():
    mi.set_variant(VARIANT)
    lgshape.register_plugins()
    yield


def sky():
    """A smooth environment: brighter towards its +y pole, varying with
    the azimuth, a little green-shifted."""
    h, w = 32, 64
    v = np.linspace(0, 1, h)[:, None, None]
    u = np.linspace(0, 2 * np.pi, w)[None, :, None]
    img = 0.3 + 0.7 * v ** 2 + 0.2 * np.cos(u) + np.zeros((h, w, 3))
    img[..., 1] *= 0.8
    return mi.Bitmap(img.astype(np.float32))


CASES = {
    "mirror": dict(expr="z - c*y", bsdf={"type": "conductor"}, eye=[0, -1.5, 2], depth=3),
    "prism": dict(expr="max(-z - 0.1, z - 0.1 - c*y)", bsdf={"type": "dielectric"},
                  eye=[0, -0.8, 2], depth=5),
}


def scene(kind, integrator, c=0.0, spp=8):
    case = CASES[kind]
    T = mi.ScalarTransform4f()
    return mi.load_dict({
        "type": "scene", "integrator": {"type": integrator, "max_depth": case["depth"]},
        "sensor": {"type": "perspective", "fov": 30,
                   "to_world": T.look_at(case["eye"], [0, 0.3, 0], [0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": 16, "height": 16,
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "env": {"type": "envmap", "bitmap": sky()},
        "obj": {"type": "lgsurface", "expr": case["expr"], "c": c,
                "bbox_min": [-4, -4, -0.5], "bbox_max": [4, 4, 0.5], "bsdf": case["bsdf"]}})


@pytest.mark.parametrize("kind", sorted(CASES))
def test01_what_a_moving_mirror_or_glass_shows_turns_with_it(kind):
    spp, seeds = (8, 2) if kind == "mirror" else (64, 6)
    fd, fd_se = central_difference(lambda c: scene(kind, "lg_path", c, spp), 0.0, 0.01, seeds)
    g, se = mean_and_se(forward_estimates(scene(kind, "lg_prb"), "obj.c", 4))
    assert abs(fd) > 10 * fd_se
    assert abs(g - fd) <= 4 * np.hypot(se, fd_se), (g, se, fd, fd_se)


def test02_the_chain_is_said():
    # Oracle: LGPRBIntegrator.uncovered names how many delta vertices are
    # followed (max_depth 3: 2) and what is still left out.
    import drjit as dr
    s = scene("mirror", "lg_prb")
    params = mi.traverse(s)
    dr.enable_grad(params["obj.c"])
    params.update()
    said = [m for m in s.integrator().uncovered(s) if "delta BSDF" in m]
    assert len(said) == 1 and "first 2 delta vertices" in said[0] and "'obj'" in said[0], said
