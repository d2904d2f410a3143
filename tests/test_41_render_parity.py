"""Renders with the lg integrators against Mitsuba's own integrators.

Oracle: Mitsuba's ``path`` and ``direct`` on native geometry. An image
differs from the reference by Monte Carlo noise only if, after a small blur,
its per-pixel differences are no larger than those between two native
renders with different seeds (the calibration, made in each test), times a
safety factor of 1.5, and the image means agree within 4 standard errors
estimated from the same pair. Same-seed renders go further: with the same
sample stream the estimators must agree to float rounding (up to a few
silhouette pixels where a float32 hit may differ). On a scene without
lgsurfaces the lg integrators' ray queries are Mitsuba's own and their
estimators do Mitsuba's float32 operations in Mitsuba's order, so each
sample's value is the same; what may differ is the order in which the film
adds a pixel's SPP samples (threads, atomics). Summed in any order, n
non-negative terms are within gamma_{n-1} = (n - 1) u / (1 - (n - 1) u)
(u = 2^-24) of their exact sum, and the box filter's weights (1 each) sum
exactly; so a pixel of the two images may differ by at most
gamma_{SPP-1} (a + b) (:func:`film_order_bound`).
"""
import lgshape  # noqa: F401  (before mitsuba: sets up libLLVM)
import mitsuba as mi
import numpy as np
import pytest
from conftest import VARIANT

RES, SPP, FACTOR = 40, 64, 1.5


@pytest.fixture(autouse=True)
def variant():
    mi.set_variant(VARIANT)
    lgshape.register_plugins()


def sphere(kind, centre, radius, bsdf):
    if kind == "native":
        return {"type": "sphere", "center": centre, "radius": radius, "bsdf": bsdf}
    return {"type": "lgsurface", "expr": "x^2 + y^2 + z^2 - 1",
            "bbox_min": [-1.05] * 3, "bbox_max": [1.05] * 3,
            "to_world": mi.ScalarTransform4f().translate(centre).scale(radius), "bsdf": bsdf}


def rgb(*v):
    return {"type": "rgb", "value": list(v)}


def diffuse(*v):
    return {"type": "diffuse", "reflectance": rgb(*v)}


def scene(integrator, kind=None):
    """Two spheres (diffuse, rough conductor) on a floor, an area light and a
    constant environment; ``kind`` None leaves the spheres out."""
    T = mi.ScalarTransform4f
    d = {"type": "scene", "integrator": integrator,
         "sensor": {"type": "perspective", "fov": 40,
                    "to_world": T().look_at([0, -5.5, 2], [0, 0, 0.1], [0, 0, 1]),
                    "film": {"type": "hdrfilm", "width": RES, "height": RES,
                             "rfilter": {"type": "box"}},
                    "sampler": {"type": "independent", "sample_count": SPP}},
         "env": {"type": "constant", "radiance": rgb(0.25, 0.3, 0.4)},
         "light": {"type": "rectangle", "flip_normals": True,
                   "to_world": T().translate([-1, -1, 3]).scale(0.6),
                   "emitter": {"type": "area", "radiance": rgb(12, 11, 9)}},
         "floor": {"type": "rectangle", "to_world": T().translate([0, 0, -1]).scale(4),
                   "bsdf": diffuse(0.5, 0.5, 0.45)},
         "box": {"type": "cube", "to_world": T().translate([1.6, 1.2, -0.6]).scale(0.4),
                 "bsdf": diffuse(0.2, 0.4, 0.7)}}
    if kind is not None:
        d["a"] = sphere(kind, [-0.75, 0, 0], 0.7, diffuse(0.7, 0.3, 0.2))
        d["b"] = sphere(kind, [0.8, 0.3, -0.1], 0.8,
                        {"type": "roughconductor", "material": "Au", "alpha": 0.25})
    return mi.load_dict(d)


def render(s, seed):
    return np.array(mi.render(s, seed=seed), dtype=np.float64)


def film_order_bound(a, b, spp=SPP):
    """The most two box-filtered renders of the same non-negative sample
    values may differ by, per pixel: each adds spp terms in its own order."""
    k = (spp - 1) * 2.0 ** -24
    return k / (1 - k) * (np.abs(a) + np.abs(b))


def blur(img):
    """3x3 box blur (edges clamped)."""
    p = np.pad(img, ((1, 1), (1, 1), (0, 0)), mode="edge")
    return sum(p[i:i + img.shape[0], j:j + img.shape[1]] for i in range(3) for j in range(3)) / 9


def metrics(a, b):
    """(mean |blurred difference|, its 99th percentile)."""
    diff = np.abs(blur(a) - blur(b))
    return np.array([diff.mean(), np.percentile(diff, 99)])


def assert_mc_equal(img, ref, ref2):
    """img vs ref within the noise measured by ref2 vs ref: blurred per-pixel
    metrics within FACTOR of the calibration's; image means within 4 standard
    errors (pixels are independent: the standard error of the difference of
    means is std(ref2 - ref) / sqrt(pixels))."""
    noise, got = metrics(ref2, ref), metrics(img, ref)
    assert np.all(got <= FACTOR * noise + 1e-6), f"blurred metrics {got} vs noise {noise}"
    se = np.std(ref2 - ref) / np.sqrt(ref.size)
    assert abs(img.mean() - ref.mean()) < 4 * se + 1e-6, (img.mean(), ref.mean(), se)


def test01_sphere_parity():
    # Oracle: native spheres with `path` (seeds 1 and 2 calibrate the noise).
    ref = render(scene({"type": "path", "max_depth": 5}, "native"), 1)
    ref2 = render(scene({"type": "path", "max_depth": 5}, "native"), 2)
    lg = scene({"type": "lg_path", "max_depth": 5}, "lg")
    assert_mc_equal(render(lg, 3), ref, ref2)
    same = np.abs(render(lg, 1) - ref).max(axis=2)
    assert np.mean(same < 1e-3) > 0.99


def test02_no_implicit_path():
    # Oracle: `path` on a scene without lgsurfaces.
    ref = render(scene({"type": "path"}), 1)
    ref2 = render(scene({"type": "path"}), 2)
    lg = scene({"type": "lg_path"})
    assert_mc_equal(render(lg, 3), ref, ref2)
    same = render(lg, 1)
    assert np.all(np.abs(same - ref) <= film_order_bound(same, ref))


@pytest.mark.parametrize("samples", [{}, {"emitter_samples": 2, "bsdf_samples": 1}])
def test03_no_implicit_direct(samples):
    # Oracle: `direct` on a scene without lgsurfaces.
    ref = render(scene({"type": "direct", **samples}), 1)
    ref2 = render(scene({"type": "direct", **samples}), 2)
    lg = scene({"type": "lg_direct", **samples})
    assert_mc_equal(render(lg, 3), ref, ref2)
    same = render(lg, 1)
    assert np.all(np.abs(same - ref) <= film_order_bound(same, ref))


def test04_sphere_direct_parity():
    # Oracle: native spheres with `direct`.
    ref = render(scene({"type": "direct"}, "native"), 1)
    ref2 = render(scene({"type": "direct"}, "native"), 2)
    assert_mc_equal(render(scene({"type": "lg_direct"}, "lg"), 3), ref, ref2)


def test05_hide_emitters():
    # Oracle: `path` with hide_emitters: the light and the sky disappear alike.
    ref = render(scene({"type": "path", "hide_emitters": True}, "native"), 1)
    ref2 = render(scene({"type": "path", "hide_emitters": True}, "native"), 2)
    assert_mc_equal(render(scene({"type": "lg_path", "hide_emitters": True}, "lg"), 3), ref, ref2)
