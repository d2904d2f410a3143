"""lg_prbvolpath's gradients in the shape of an lgsurface that bounds a
homogeneous medium with a 'null' BSDF (a fog ball's radius), and its
refusals where a moving lgsurface's shape is not covered.

Oracles:
- an absorbing fog ball (albedo 0) against a constant sky of radiance 1:
  each camera ray's radiance is exp(-sigma_t c), c its chord through the
  ball, in closed form from the ray's distance to the centre; the image
  mean is its mean over the film (box filter), integrated on a
  4000 x 4000 midpoint grid in float64, and d mean / d r its central
  difference (step 1e-3; the grid's and the step's errors are below 1e-4);
  a uniform scale s in ``to_world`` makes it the ball of radius s r, whose
  derivative at s = 1 is r times the radius's;
- a scattering fog ball (albedo 0.8) lit by a directional light: central
  finite differences of lg_volpath's image mean (the estimator
  lg_prbvolpath differentiates), h = 0.01, the same seed on both sides.
lg_prbvolpath's estimate (reverse mode) over independent seeds; agreement
within K standard errors of the difference. With the ends' scattering term
off (``medium_band`` 0), the scattering ball's estimate is far from the
finite differences: the term is what makes it right.
"""
from __future__ import annotations

import drjit as dr
import lgshape
import mitsuba as mi
import numpy as np
import pytest

from conftest import VARIANT
from gradient_oracles import central_difference, mean_and_se

K = 4.0
R, SIGMA_T = 0.5, 2.0
EYE = (0.0, 0.3, 3.0)
FOV = 40.0


@pytest.fixture(scope="module", autouse=True)
def variant():
    mi.set_variant(VARIANT)
    lgshape.register_plugins()
    yield


def fog_ball(integrator, r=R, albedo=0.0, sun=False, spp=64, res=16, bsdf=None,
             medium=None, fov=FOV, **props):
    ball = {"type": "lgsurface", "expr": "x^2 + y^2 + z^2 - r^2", "r": r,
            "bbox_min": [-0.7] * 3, "bbox_max": [0.7] * 3,
            "bsdf": bsdf or {"type": "null"},
            "interior": medium or {"type": "homogeneous", "sigma_t": SIGMA_T,
                                   "albedo": {"type": "rgb", "value": [albedo] * 3}}}
    d = {"type": "scene", "integrator": {"type": integrator, "max_depth": 8, **props},
         "sensor": {"type": "perspective", "fov": fov,
                    "to_world": mi.ScalarTransform4f().look_at(list(EYE), [0, 0, 0],
                                                               [0, 1, 0]),
                    "film": {"type": "hdrfilm", "width": res, "height": res,
                             "rfilter": {"type": "box"}},
                    "sampler": {"type": "independent", "sample_count": spp}},
         "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 0.2 if sun else 1.0}},
         "ball": ball}
    if sun:
        d["sun"] = {"type": "directional", "direction": [-0.4, -1, -0.3],
                    "irradiance": {"type": "rgb", "value": 3.0}}
    return mi.load_dict(d)


def reverse_estimates(scene, key, seeds):
    params = mi.traverse(scene)
    out = []
    for k in range(seeds):
        dr.enable_grad(params[key])
        params.update()
        img = mi.render(scene, params, seed=2 * k + 5, seed_grad=2 * k + 6)
        dr.backward(dr.mean(img, axis=None))
        out.append(float(dr.grad(params[key])[0]))
        dr.set_grad(params[key], 0)
    return np.array(out)


def absorbing_mean(r, fov, n=4000):
    """The image mean of the absorbing ball against the sky, by quadrature
    over the film: a ray at film point (x, y) in [-1, 1]^2 makes the angle
    a with the axis, tan a = |(x, y)| tan(fov / 2); its distance to the
    centre is D sin a, its chord 2 sqrt(r^2 - D^2 sin^2 a)."""
    tan = np.tan(np.radians(fov) / 2)
    x = (np.arange(n) + 0.5) / n * 2 - 1
    X, Y = np.meshgrid(x, x)
    u2 = (X * X + Y * Y) * tan * tan
    b2 = np.dot(EYE, EYE) * u2 / (1 + u2)
    chord = 2 * np.sqrt(np.maximum(r * r - b2, 0.0))
    return float(np.exp(-SIGMA_T * chord).mean())


def test01_absorbing_fog_ball_against_its_closed_form():
    # The film sees the ball's middle only (fov 10 degrees: the rays pass
    # within 0.27 of the centre): near a silhouette the chord's derivative
    # grows as 1 / sqrt(r - b), and the estimate's variance without bound
    # (logarithmically), so that the seeds' spread would understate it.
    h, fov = 1e-3, 10.0
    exact = (absorbing_mean(R + h, fov) - absorbing_mean(R - h, fov)) / (2 * h)
    g, se = mean_and_se(reverse_estimates(fog_ball("lg_prbvolpath", spp=64, fov=fov),
                                          "ball.r", 16))
    assert exact < -0.5
    assert abs(g - exact) <= K * se + 1e-4, (g, se, exact)


def test02_a_scale_in_to_world_is_the_radius_times_r():
    # The ball x^2 + y^2 + z^2 = r^2 scaled by s about its centre is the
    # ball of radius s r: d mean / d s at s = 1 is r d mean / d r (the
    # closed form of test01).
    h, fov = 1e-3, 10.0
    exact = R * (absorbing_mean(R + h, fov) - absorbing_mean(R - h, fov)) / (2 * h)
    s = fog_ball("lg_prbvolpath", spp=64, fov=fov)
    params = mi.traverse(s)
    out = []
    for k in range(16):
        x = mi.Float(1.0)
        dr.enable_grad(x)
        params["ball.to_world"] = mi.Transform4f().scale(mi.Vector3f(x))
        params.update()
        img = mi.render(s, params, seed=2 * k + 5, seed_grad=2 * k + 6)
        dr.backward(dr.mean(img, axis=None))
        out.append(float(dr.grad(x)[0]))
    g, se = mean_and_se(out)
    assert abs(g - exact) <= K * se + 1e-4, (g, se, exact)


def test03_scattering_fog_ball_against_finite_differences():
    fd, fd_se = central_difference(
        lambda r: fog_ball("lg_volpath", r, albedo=0.8, sun=True, spp=1024), R, 0.01, 8)
    on = reverse_estimates(fog_ball("lg_prbvolpath", albedo=0.8, sun=True), "ball.r", 16)
    off = reverse_estimates(fog_ball("lg_prbvolpath", albedo=0.8, sun=True, medium_band=0.0),
                            "ball.r", 16)
    g, se = mean_and_se(on)
    g_off, se_off = mean_and_se(off)
    assert abs(fd) > 10 * fd_se
    assert abs(g - fd) <= K * np.hypot(se, fd_se), (g, se, fd, fd_se)
    assert abs(g_off - fd) > 2 * K * np.hypot(se_off, fd_se), (g_off, se_off, fd, fd_se)


@pytest.mark.parametrize("case", ["diffuse", "heterogeneous"])
def test04_uncovered_shapes_raise(case):
    from lgshape.plugins.checks import NotDifferentiableError
    if case == "diffuse":
        s = fog_ball("lg_prbvolpath", spp=4, res=4, bsdf={"type": "diffuse"})
        why = "BSDF is not 'null'"
    else:
        grid = {"type": "gridvolume", "grid": mi.VolumeGrid(np.full((2, 2, 2, 1), 2.0,
                                                                    np.float32))}
        s = fog_ball("lg_prbvolpath", spp=4, res=4,
                     medium={"type": "heterogeneous", "sigma_t": grid,
                             "albedo": {"type": "rgb", "value": 0.5}})
        why = "interior medium is heterogeneous"
    params = mi.traverse(s)
    dr.enable_grad(params["ball.r"])
    params.update()
    with pytest.raises(NotDifferentiableError) as err:
        mi.render(s, params, seed=1)
    assert "'ball.r'" in str(err.value) and why in str(err.value), str(err.value)
