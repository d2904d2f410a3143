"""lg_prb says which terms of a gradient it leaves out, and covers those it
can: the render-time warnings (LGPRBIntegrator.uncovered), the primary
silhouettes behind hidden emitters, the textured native emitters' samples.

Oracles: the warnings' conditions as the integrator's docstring states
them (which scene leaves out which term), each warning counted over
several gradient passes; a closed form (the image mean of a black ball in
front of a backdrop lit symmetrically about the view axis); Mitsuba's prb
on a scene of native shapes only (the same samples: the same gradient
image to rounding).
"""
from __future__ import annotations

import warnings

import drjit as dr
import lgshape
import mitsuba as mi
import numpy as np
import pytest

from conftest import VARIANT

U = 2.0 ** -24
ROUND = 256


@pytest.fixture(scope="module", autouse=True)
def variant():
    mi.set_variant(VARIANT)
    lgshape.register_plugins()
    yield


def sensor(origin, target, fov=30, res=8, spp=2):
    return {"type": "perspective", "fov": fov,
            "to_world": mi.ScalarTransform4f().look_at(origin, target, [0, 1, 0]),
            "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}},
            "sampler": {"type": "independent", "sample_count": spp}}


def diffuse(rho):
    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": rho}}


def ball(r, at=(0, 0, 0)):
    return {"type": "lgsurface", "expr": "x^2 + y^2 + z^2 - r^2", "r": r,
            "bbox_min": [-1, -1, -1], "bbox_max": [1, 1, 1],
            "to_world": mi.ScalarTransform4f().translate(list(at)), "bsdf": diffuse(0.5)}


def floor():
    return {"type": "rectangle", "bsdf": diffuse(0.8),
            "to_world": mi.ScalarTransform4f().translate([0, -1, 0])
            @ mi.ScalarTransform4f().rotate([1, 0, 0], -90) @ mi.ScalarTransform4f().scale(3)}


def scene(name, max_depth=2, emits=False, lamp=False, mirror=False, sheet=False, **props):
    """A ball (or an open sheet) with id ``name`` above a floor under the
    sky; options: it emits, another lgsurface emits, a mirror beside it."""
    obj = ball(0.4)
    if sheet:
        obj = {"type": "lgsurface", "expr": "y - c", "c": 0.0, "bsdf": diffuse(0.5),
               "bbox_min": [-0.5, -0.2, -0.5], "bbox_max": [0.5, 0.2, 0.5]}
    if emits:
        obj["emitter"] = {"type": "area", "radiance": {"type": "rgb", "value": 2.0}}
    d = {"type": "scene",
         "integrator": {"type": "lg_prb", "max_depth": max_depth, **props},
         "sensor": sensor([0, 1, 4], [0, 0, 0]),
         "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 0.3}},
         "floor": floor(), name: obj}
    if lamp:
        d["lamp"] = {**ball(0.2, (1, 1, 0)),
                     "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 5.0}}}
    if mirror:
        d["mirror"] = {"type": "rectangle", "bsdf": {"type": "conductor"},
                       "to_world": mi.ScalarTransform4f().translate([-1.2, 0, 0])
                       @ mi.ScalarTransform4f().rotate([0, 1, 0], 90)}
    return mi.load_dict(d)


def moving(s, key):
    params = mi.traverse(s)
    dr.enable_grad(params[key])
    params.update()
    return params


def said(fn):
    """fn() with every LGShapeWarning recorded: their messages."""
    from lgshape.plugins import LGShapeWarning
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        fn()
    return [str(w.message) for w in seen if issubclass(w.category, LGShapeWarning)]


BOUNCE = "(in mirrors, through glass, in interreflections)"
CUT = "reaches its bounding box"


@pytest.mark.parametrize("name, options, key, expected", [
    ("bounced", {"max_depth": 4, "bounce_edges": 2}, "r", [BOUNCE, "max_depth 4"]),
    ("unbounded", {"max_depth": -1}, "r", [BOUNCE, "max_depth -1"]),
    ("mirrored", {"mirror": True, "bounce_edges": 0}, "r",
     [BOUNCE, "delta or null BSDF of 'mirror'"]),
    ("sheet", {"sheet": True}, "c", [CUT]),
])
def test01_each_left_out_term_is_said_once(name, options, key, expected):
    # Oracle: the conditions of LGPRBIntegrator.uncovered: each scene
    # leaves out exactly one kind of term, said once (naming the surface
    # and the term) over two forward passes and a backward pass.
    s = scene(name, **options)
    params = moving(s, f"{name}.{key}")

    def passes():
        for _ in range(2):
            img = mi.render(s, params, seed=1, seed_grad=2)
            dr.forward(params[f"{name}.{key}"])
        img = mi.render(s, params, seed=1, seed_grad=2)
        dr.backward(dr.mean(img, axis=None))
    messages = [m for m in said(passes) if m.startswith("lg_prb:")]
    assert len(messages) == 1, messages
    assert f"'{name}'" in messages[0] and "left out" in messages[0]
    for part in expected:
        assert part in messages[0], messages[0]


@pytest.mark.parametrize("name, options, key", [
    ("plain", {}, "r"),                                  # max_depth 2, smooth BSDFs
    ("camera", {"max_depth": 1, "emits": True, "mirror": True, "lamp": True}, "obj"),
    ("still", {"max_depth": 3, "emits": True, "mirror": True, "lamp": True}, "bsdf"),
    ("off", {"max_depth": 3, "mirror": True, "lamp": True, "sheet": True, "boundary": False},
     "c"),
    ("no_edges", {"lamp": True, "shadow_edges": False}, "r"),
    ("glowing", {"emits": True}, "r"),                   # its light follows it (test_61)
    ("reflected", {"max_depth": 3, "mirror": True}, "r"),  # bounce_edges 2 (test_62)
    ("shading", {"lamp": True}, "r"),                    # its shadows on the lamp too
])
def test02_nothing_said_where_nothing_is_left_out(name, options, key):
    # Oracle: the same conditions: max_depth 2 with smooth BSDFs only and
    # no emitter on an lgsurface; max_depth 1 (the camera sees the
    # emitters, whose primary silhouettes have their term, and nothing
    # else: no light reaches a surface); a gradient on a BSDF
    # only (no moving lgsurface); boundary terms off (none is asked for);
    # shadow edges off; an emitting lgsurface that moves, or one that
    # lights a moving one, at max_depth 2 (its light's interior and edge
    # terms are computed: test_61); max_depth 3 with a mirror, whose two
    # bounces have the bounce term (bounce_edges 2: test_62).
    s = scene(name, **options)
    key = {"obj": f"{name}.r", "bsdf": "floor.bsdf.reflectance.value"}.get(key, f"{name}.{key}")
    params = moving(s, key)

    def passes():
        img = mi.render(s, params, seed=1, seed_grad=2)
        dr.forward(params[key])
    messages = [m for m in said(passes) if m.startswith("lg_prb:")]
    assert messages == [], messages


def test03_silhouette_behind_a_hidden_emitter():
    # Oracle: the closed form. A black ball (radius r, distance D from the
    # camera) in front of a diffuse backdrop (albedo 0.8) lit by a point
    # light on the view axis between them, so that the backdrop's radiance
    # L_b is the same all along the silhouette's image (a circle of radius
    # tan a, tan a = r / sqrt(D^2 - r^2)); an emitting panel hides the left
    # part of the view, invisible under hide_emitters (its emission faces
    # the camera and lights nothing). The image mean's derivative is
    # -L_b 2 pi tan a d(tan a)/dr / (2 tan 15 deg)^2, all of it the
    # silhouette's, behind the panel too (without it, about half). Within
    # 4 standard errors over 8 seeds (the relaxation's bias, below 1% here,
    # is far below them).
    r, D, zl, intensity, half = 0.6, 4.0, -1.0, 1.0, np.tan(np.radians(15))

    def make(v=r):
        return mi.load_dict({
            "type": "scene",
            "integrator": {"type": "lg_prb", "max_depth": 2, "hide_emitters": True},
            "sensor": sensor([0, 0, D], [0, 0, 0], res=32, spp=64),
            "lamp": {"type": "point", "position": [0, 0, zl],
                     "intensity": {"type": "rgb", "value": intensity}},
            "back": {"type": "rectangle", "bsdf": diffuse(0.8),
                     "to_world": mi.ScalarTransform4f().translate([0, 0, -2])
                     @ mi.ScalarTransform4f().scale(3)},
            "veil": {"type": "rectangle",
                     "to_world": mi.ScalarTransform4f().translate([-0.5, 0, 3])
                     @ mi.ScalarTransform4f().scale(0.5),
                     "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 0.3}}},
            "hidden_veil_ball": {**ball(v), "bsdf": diffuse(0.0)}})
    tan_a = r / np.sqrt(D * D - r * r)
    dtan = D * D / (D * D - r * r) ** 1.5
    rb, h = tan_a * (D + 2), zl + 2                       # where the silhouette's rays
    d2 = rb * rb + h * h                                  # meet the backdrop
    L_b = 0.8 / np.pi * intensity * (h / np.sqrt(d2)) / d2
    expected = -L_b * np.pi * 2 * tan_a * dtan / (2 * half) ** 2
    out = []
    for k in range(8):
        s = make()
        params = moving(s, "hidden_veil_ball.r")
        img = mi.render(s, params, seed=2 * k + 100, seed_grad=2 * k + 101)
        dr.forward(params["hidden_veil_ball.r"])
        out.append(float(np.mean(np.array(dr.grad(img), np.float64))))
    g, se = float(np.mean(out)), float(np.std(out, ddof=1) / np.sqrt(len(out)))
    assert abs(g - expected) <= 4 * se, (g, se, expected)


def test04_textured_native_emitter_is_prbs():
    # Oracle: Mitsuba's prb on a scene of native shapes only (a floor lit by
    # a panel whose emission is a bilinear ramp, the panel translated along
    # its ramp): prb intersects each emitter sample again so that its uv
    # follows the panel, and lg_prb does the same: the same gradient image
    # to rounding (the same samples; an lgsurface out of every path does
    # not change them).
    ramp = np.tile(np.linspace(0.2, 3.0, 8, dtype=np.float32)[None, :, None], (8, 1, 3))

    def make(integrator):
        return mi.load_dict({
            "type": "scene", "integrator": {"type": integrator, "max_depth": 2},
            "sensor": sensor([0, 2, 2], [0, 0, 0], fov=40, res=16, spp=16),
            "floor": {"type": "rectangle", "bsdf": diffuse(0.8),
                      "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90)
                      @ mi.ScalarTransform4f().scale(2)},
            "panel": {"type": "rectangle", "emitter": {
                "type": "area", "radiance": {"type": "bitmap", "bitmap": mi.Bitmap(ramp),
                                             "raw": True}}},
            **({"far": ball(0.2, (3, 3, 3))} if integrator == "lg_prb" else {})})

    def gradient(s):
        params = mi.traverse(s)
        x = mi.Float(0.0)
        dr.enable_grad(x)
        params["panel.to_world"] = mi.Transform4f().translate(mi.Vector3f(x, 1.0, 0)) \
            @ mi.Transform4f().rotate([1, 0, 0], 90) @ mi.Transform4f().scale(0.5)
        params.update()
        img = mi.render(s, params, seed=3, seed_grad=7)
        dr.forward(x)
        return np.array(dr.grad(img), np.float64)
    g_prb, g_lg = gradient(make("prb")), gradient(make("lg_prb"))
    assert np.abs(g_prb).max() > 0.1
    assert np.all(np.abs(g_prb - g_lg) <= ROUND * U * (np.abs(g_prb) + np.abs(g_prb).max()))
