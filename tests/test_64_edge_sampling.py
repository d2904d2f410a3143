"""The sampling of lg_prb's boundary terms: the silhouette term's stratified
camera rays and the edges' band weights.

Oracles: exact enumeration (which grid cell of its pixel each film
position falls in; every position inside its own pixel), the sensor's own
ray for each position, and the weights' moments by Gauss-Legendre
quadrature on each smooth piece against their closed forms (band_weight:
integral 1; edge_weight: integral 1, first moment 0, mean square 4 /
width^2). The terms' gradients against finite differences and closed forms
are test_46's (shadow edges), test_61's (light edges) and test_62's.
"""
from __future__ import annotations

import drjit as dr
import lgshape
import mitsuba as mi
import numpy as np
import pytest

from conftest import VARIANT


@pytest.fixture(scope="module", autouse=True)
def variant():
    mi.set_variant(VARIANT)
    lgshape.register_plugins()
    yield


def scene_dict(res_x=5, res_y=3, spp=9, rfilter="box", extra=None):
    d = {"type": "scene", "integrator": {"type": "lg_prb", "max_depth": 3},
         "sensor": {"type": "perspective", "fov": 40,
                    "to_world": mi.ScalarTransform4f().look_at([0, -3, 2], [0, 0, 0.3],
                                                               [0, 0, 1]),
                    "film": {"type": "hdrfilm", "width": res_x, "height": res_y,
                             "rfilter": {"type": rfilter}},
                    "sampler": {"type": "independent", "sample_count": spp}},
         "ball": {"type": "lgsurface", "expr": "x^2 + y^2 + (z - 0.45)^2 - r^2", "r": 0.4,
                  "bbox_min": [-0.7, -0.7, -0.25], "bbox_max": [0.7, 0.7, 1.15]}}
    d.update(extra or {})
    return d


@pytest.mark.parametrize("spp", [9, 5, 16])
def test01_stratified_rays_fill_each_pixel(spp):
    """Each pixel's spp positions lie in that pixel, in distinct cells of a
    k x k grid (k^2 >= spp), and each ray is the sensor's for its position."""
    res_x, res_y = 5, 3
    scene = mi.load_dict(scene_dict(res_x, res_y, spp, rfilter="gaussian"))
    integrator = scene.integrator()
    sensor = scene.sensors()[0]
    sampler, spp_ = integrator.prepare(sensor, 7, spp, [])
    assert spp_ == spp
    ray, weight, pos = integrator._stratified_rays(scene, sensor, sampler, 7)
    p = np.array(pos, np.float64).T if np.array(pos).shape[0] == 2 else np.array(pos)
    assert p.shape == (res_x * res_y * spp, 2)
    k = int(np.ceil(np.sqrt(spp)))
    pixel = np.arange(res_x * res_y * spp) // spp
    px, py = pixel % res_x, pixel // res_x
    assert np.all((p[:, 0] >= px) & (p[:, 0] < px + 1))
    assert np.all((p[:, 1] >= py) & (p[:, 1] < py + 1))
    cells = np.floor((p[:, 0] - px) * k) + k * np.floor((p[:, 1] - py) * k)
    for q in range(res_x * res_y):
        mine = cells[pixel == q]
        assert len(set(mine.tolist())) == spp          # distinct cells
    # the sensor's ray at those positions
    ref, _ = sensor.sample_ray_differential(
        0.0, 0.0, mi.Point2f(p[:, 0] / res_x, p[:, 1] / res_y), mi.Point2f(0.5))
    assert np.allclose(np.array(ray.d), np.array(ref.d), atol=1e-6)


def test02_box_filter_splats_at_the_pixel():
    scene = mi.load_dict(scene_dict(4, 4, 4))
    integrator = scene.integrator()
    sensor = scene.sensors()[0]
    sampler, _ = integrator.prepare(sensor, 3, 4, [])
    _, _, pos = integrator._stratified_rays(scene, sensor, sampler, 3)
    p = np.array(pos)
    assert np.all(p == np.floor(p))


def _moments(weight, width, pieces):
    """int w, int w (-S), int w^2 over the band, by Gauss-Legendre on each
    smooth piece ((a, b) in S)."""
    x, wq = np.polynomial.legendre.leggauss(40)
    m = np.zeros(3)
    for a, b in pieces:
        S = 0.5 * (b - a) * x + 0.5 * (a + b)
        w = np.array(weight(mi.Float(S.astype(np.float32)), width), np.float64)
        h = 0.5 * (b - a) * wq
        m += [np.sum(h * w), np.sum(h * w * -S), np.sum(h * w * w)]
    return m


def test03_band_weights_moments():
    from lgshape.plugins.lgsurface import band_weight, edge_weight
    width = 0.3
    m0, m1, m2 = _moments(edge_weight, width, [(-width, 0.0)])
    tol = 1e-5 * 4 / width
    assert abs(m0 - 1) < tol and abs(m1) < tol * width
    assert abs(m2 - 4 / width) < tol * 4 / width * 10
    m0, _, m2b = _moments(band_weight, width, [(-width, -width / 4), (-width / 4, 0.0)])
    assert abs(m0 - 1) < tol
    assert m2b > 3.5 * m2                               # 15.3 / width against 4 / width
