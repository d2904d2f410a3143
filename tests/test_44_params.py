"""Scene parameters of ``lgsurface`` (``mi.traverse`` / ``params.update()``).

Oracles:
- a fresh ``mi.load_dict`` of the scene with the new values: the render
  after an update must equal it bit for bit at the same seed (box
  reconstruction filter: Mitsuba's default Gaussian filter accumulates
  samples from several threads in a varying order, so even two identical
  renders may differ in the last bit);
- the closed form of a ray-sphere distance in float64 for the depth AOV
  after the sphere's radius changed;
- Dr.Jit's kernel history: the JIT kernels of a render after an update have
  the same hashes as before it (nothing recompiles);
- object identity / the build counter of the shape: a new ``to_world`` does
  not rebuild the Surface.
"""
import math

import lgshape  # noqa: F401  (before mitsuba: sets up libLLVM)
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from lgshape.expr.parser import ParseError, free_names, parse
from conftest import VARIANT

RES = 24
BOX = {"bbox_min": [-1.1, -1.1, -1.1], "bbox_max": [1.1, 1.1, 1.1]}
BALL = {"type": "lgsurface", "expr": "x^2 + y^2 + z^2 - radius^2", "radius": 1.0, **BOX}
TORUS = {"type": "lgsurface", "surface": "torus", "R": 0.9}


@pytest.fixture(autouse=True)
def variant():
    mi.set_variant(VARIANT)
    lgshape.register_plugins()


def path_scene(shape, res=RES, spp=4):
    """lg_path, a point light and a constant environment (whose bounding
    sphere follows the scene's bounds), box filter."""
    return mi.load_dict({
        "type": "scene",
        "integrator": {"type": "lg_path", "max_depth": 3},
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at([0.4, -5, 1.5], [0, 0, 0],
                                                              [0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": res, "height": res,
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "env": {"type": "constant", "radiance": 0.3},
        "light": {"type": "point", "position": [2.0, -3.0, 3.0], "intensity": 15.0},
        "s": shape})


def depth_scene(shape, res=25):
    """lg_aov depth through the pixel centres (1 spp, no jitter, box filter)."""
    return mi.load_dict({
        "type": "scene",
        "integrator": {"type": "lg_aov", "aovs": "dd:depth"},
        "sensor": {"type": "perspective", "fov": 30,
                   "to_world": mi.ScalarTransform4f().look_at([0, -5, 0], [0, 0, 0], [0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": res, "height": res,
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "stratified", "sample_count": 1, "jitter": False}},
        "s": shape})


def render(scene):
    return np.array(mi.render(scene, seed=3), dtype=np.float32)


def shape_of(scene):
    return [s for s in scene.shapes() if getattr(s, "IS_LGSURFACE", False)][0]


def transform():
    return (mi.ScalarTransform4f().translate([0.3, -0.2, 0.4])
            @ mi.ScalarTransform4f().rotate([0.3, 0.5, 0.8], 40)
            @ mi.ScalarTransform4f().scale([1.2, 0.7, 0.9]))


# ---------------------------------------------------------------------------
#  Named constants in the parser
# ---------------------------------------------------------------------------

def test01_parser_named_constants():
    # Oracle: the same text with the number written in place of the name.
    assert free_names("x^2 + y^2 + z^2 - radius^2 + k*sin(pi*x) + radius") == \
        [("radius", 18), ("k", 29)]
    # (named constants stay leaves of their own, never folded: the same
    # function, compared by value at sample points)
    from lgshape.arraymath import NUMPY
    from lgshape.expr import evaluate
    p = np.random.default_rng(0).uniform(-2, 2, (100, 3))
    env = {v: p[:, i] for i, v in enumerate("xyz")}
    for text, consts, plain in (("x^2 + y^2 + z^2 - radius^2", {"radius": 0.5},
                                 "x^2 + y^2 + z^2 - 0.5^2"),
                                ("x^n - a", {"n": 3, "a": -2.5}, "x^3 - -2.5")):
        assert np.array_equal(evaluate(parse(text, constants=consts), env, NUMPY),
                              evaluate(parse(plain), env, NUMPY))
    with pytest.raises(ParseError, match=r"unknown identifier 'w' .*bound constants: a.* "
                                         r"at position 7") as err:
        parse("x + 2*w", constants={"a": 1.0})
    assert err.value.identifier == "w" and err.value.pos == 6
    for bad, message in (({"x": 1.0}, "cannot be bound"), ({"sin": 1.0}, "cannot be bound"),
                         ({"r": math.nan}, "not finite"), ({"r": True}, "must be a number"),
                         ({"2r": 1.0}, "not an identifier")):
        with pytest.raises(ValueError, match=message):
            parse("x", constants=bad)


# ---------------------------------------------------------------------------
#  mi.traverse
# ---------------------------------------------------------------------------

def test02_traverse_library_surface():
    # Oracle: the library function's numeric parameters (torus: R, r = 0.4
    # by default) as float32 (Mitsuba's scene parameters), the loaded
    # transform; geometry's flags (differentiable, discontinuous).
    T = transform()
    params = mi.traverse(mi.load_dict({"type": "scene", "s": {**TORUS, "to_world": T}}))
    assert {"s.to_world", "s.R", "s.r"} <= set(params.keys())
    assert params["s.R"][0] == np.float32(0.9) and params["s.r"][0] == np.float32(0.4)
    assert isinstance(params["s.R"], mi.Float)
    assert isinstance(params["s.to_world"], mi.AffineTransform4f)
    assert np.array_equal(np.array(params["s.to_world"].matrix)[..., 0], np.array(T.matrix))
    for k in ("s.to_world", "s.R", "s.r"):
        assert params.flags(k) & mi.ParamFlags.Discontinuous
        assert not params.flags(k) & mi.ParamFlags.NonDifferentiable
    assert "s.bsdf.reflectance.value" in params           # the BSDF stays reachable


def test03_traverse_expr_constants(tmp_path):
    # Oracle: the identifiers of the expression other than x, y, z, pi, e and
    # functions, with their property values.
    scene = mi.load_dict({"type": "scene", "s": {
        "type": "lgsurface", "expr": "x^2 + y^2 + (z - lift)^2 - radius^2 + 0*pi",
        "radius": 0.8, "lift": 0.25, **BOX}})
    params = mi.traverse(scene)
    for k in ("s.radius", "s.lift", "s.to_world"):
        assert k in params and params.flags(k) & mi.ParamFlags.Discontinuous
    assert not any(k in params for k in ("s.pi", "s.e", "s.x"))
    assert params["s.radius"][0] == np.float32(0.8) and params["s.lift"][0] == 0.25
    # the same from an expr_file
    (tmp_path / "f.txt").write_text("x^2 + y^2 + z^2 - radius^2\n")
    params = mi.traverse(mi.load_dict({"type": "scene", "s": {
        "type": "lgsurface", "expr_file": str(tmp_path / "f.txt"), "radius": 0.6, **BOX}}))
    assert params["s.radius"][0] == np.float32(0.6)


@pytest.mark.parametrize("props, message", [
    ({"expr": "x^2 + y^2 + z^2 - radius^2", **BOX},
     r"malformed 'expr': unknown identifier 'radius' .* at position 19:(.|\n)*"
     r"<float name=\"radius\""),
    ({"expr": "x^2 + y^2 + z^2 - radius^2", "radius": 1.0, "unused": 2.0, **BOX},
     r"unknown parameter 'unused'.*known parameters: .*radius.*named constant only where"),
    ({"expr": "x - depth", "depth": 4, **BOX},
     r"the name 'depth' cannot be a named constant: it is a parameter of lgsurface"),
    ({"expr": "x - faces", **BOX}, r"the name 'faces' cannot be a named constant"),
    ({"expr": "x - a", "a": "one", **BOX}, r"'a' is a named constant .* not a finite number"),
])
def test04_constant_errors(props, message):
    # Oracle: the documented messages (identifier, 1-based position, hint).
    with pytest.raises(Exception, match=message):
        mi.load_dict({"type": "scene", "s": {"type": "lgsurface", **props}})


# ---------------------------------------------------------------------------
#  params.update()
# ---------------------------------------------------------------------------

def test05_expr_constant_update_equals_fresh_load():
    # Oracle: a fresh load with the new value, bit for bit.
    scene = path_scene(BALL)
    shape = shape_of(scene)
    before, surface = render(scene), shape.surface
    params = mi.traverse(scene)
    params["s.radius"] = 0.6
    params.update()
    after = render(scene)
    fresh = render(path_scene({**BALL, "radius": 0.6}))
    assert np.array_equal(after, fresh)
    assert not np.array_equal(after, before)
    assert shape.surface is not surface and shape.builds == 2
    assert np.allclose(shape.surface.bbox, ((-1.1,) * 3, (1.1,) * 3))
    # Setting it back gives the first image again.
    params["s.radius"] = 1.0
    params.update()
    assert np.array_equal(render(scene), before)


def test06_library_update_and_bounds():
    # Oracle: a fresh load with the new values (the library box grows with R).
    scene = path_scene(TORUS)
    before = render(scene)                   # fills the shape's caches
    params = mi.traverse(scene)
    params["s.R"] = 1.1
    params["s.r"] = 0.3
    params.update()
    fresh_scene = path_scene({**TORUS, "R": 1.1, "r": 0.3})
    assert np.array_equal(render(scene), render(fresh_scene))
    assert shape_of(scene).surface.bbox == shape_of(fresh_scene).surface.bbox
    assert np.allclose(np.array(scene.bbox().max), np.array(fresh_scene.bbox().max))
    assert shape_of(scene).builds == 2       # one update of two keys: one rebuild
    assert not np.array_equal(render(scene), before)


def test07_to_world_update_keeps_surface():
    # Oracle: a fresh load with the new transform; the Surface object is
    # the same (and the build count unchanged).
    scene = path_scene(TORUS)
    shape = shape_of(scene)
    surface = shape.surface
    before = render(scene)                   # fills the shape's caches
    params = mi.traverse(scene)
    params["s.to_world"] = transform()
    params.update()
    assert shape.surface is surface and shape.builds == 1
    fresh_scene = path_scene({**TORUS, "to_world": transform()})
    assert np.array_equal(render(scene), render(fresh_scene))
    assert np.array_equal(np.array(scene.bbox().min), np.array(fresh_scene.bbox().min))
    assert np.array_equal(np.array(scene.bbox().max), np.array(fresh_scene.bbox().max))
    assert not np.array_equal(render(scene), before)
    # An update of another part of the scene rebuilds nothing.
    params["s.bsdf.reflectance.value"] = 0.25
    params.update()
    assert shape.surface is surface and shape.builds == 1


def test08_kernels_reused_after_update():
    # Oracle: Dr.Jit's kernel history; every JIT kernel of the render after
    # an update of a constant (and of to_world) has the hash of one before.
    scene = path_scene(BALL)
    params = mi.traverse(scene)
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        def hashes():
            dr.kernel_history()                                  # clear
            render(scene)
            return [k["hash"] for k in dr.kernel_history([dr.KernelType.JIT])]
        first = hashes()
        params["s.radius"] = 0.7
        params.update()
        second = hashes()
        params["s.to_world"] = transform()
        params.update()
        third = hashes()
    assert first and first == second == third


def test09_depth_after_radius_update():
    # Oracle: the distance from the camera along each pixel-centre ray to the
    # sphere |p| = r, in float64 closed form.
    scene = depth_scene(BALL)
    sensor = scene.sensors()[0]
    res = sensor.film().size()[0]
    j, i = np.meshgrid(np.arange(res), np.arange(res))
    pos = mi.Point2f(((j.ravel() + 0.5) / res).astype(np.float32),
                     ((i.ravel() + 0.5) / res).astype(np.float32))
    ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5, 0.5))
    o, d = np.array(ray.o, np.float64).T, np.array(ray.d, np.float64).T

    def check(r):
        img = np.array(mi.render(scene), np.float64)[..., -1].ravel()
        b = np.sum(o * d, 1)
        disc = b * b - (np.sum(o * o, 1) - r * r)
        t = -b - np.sqrt(np.maximum(disc, 0))
        hit, miss = disc > 1e-3, disc < -1e-3
        assert hit.sum() > 20
        assert np.max(np.abs(img[hit] - t[hit])) < 2e-5
        assert np.all(img[miss] == 0)
        # The centre pixel looks at the centre: 5 - r from the camera, whose
        # rays start on the near clipping plane.
        c = (res // 2) * res + res // 2
        assert abs(img[c] + np.linalg.norm(o[c] - [0, -5, 0]) - (5.0 - r)) < 2e-5
    check(1.0)
    params = mi.traverse(scene)
    params["s.radius"] = 0.5
    params.update()
    check(0.5)


def test10_invalid_update_is_refused_and_undone():
    # Oracle: the values in use before the update (parameters and image).
    scene = path_scene(BALL, res=12, spp=2)
    before = render(scene)
    params = mi.traverse(scene)
    params["s.radius"] = math.nan
    with pytest.raises(ValueError, match=r"parameter 'radius' must be finite"):
        params.update()
    assert params["s.radius"][0] == 1.0
    params["s.to_world"] = mi.ScalarTransform4f().scale([1.0, 0.0, 1.0])
    with pytest.raises(ValueError, match=r"'to_world' is not invertible"):
        params.update()
    assert np.array_equal(np.array(params["s.to_world"].matrix)[..., 0], np.eye(4))
    assert np.array_equal(render(scene), before)
    assert shape_of(scene).builds == 1


def test11_primitives_smoothness(tmp_path):
    # Oracle: a fresh load with the new smoothness.
    path = tmp_path / "p.txt"
    path.write_text("sphere -0.4 0 0 0.5\nsphere 0.4 0 0 0.5\nsphere 0 0 0.5 0.4\n")
    shape = {"type": "lgsurface", "primitives": str(path), "combine": "smooth_union",
             "smoothness": 0.1}
    scene = depth_scene(shape, res=16)
    params = mi.traverse(scene)
    assert params["s.smoothness"][0] == np.float32(0.1)
    params["s.smoothness"] = 0.3
    params.update()
    fresh = depth_scene({**shape, "smoothness": 0.3}, res=16)
    assert np.array_equal(render(scene), render(fresh))


def test12_infinite_emitters_follow_new_bounds():
    # Oracle: a fresh load. Mitsuba 3.9.1's Scene.parameters_changed gives
    # an environment emitter the bounds from before the update and never
    # informs a directional one; the lg integrators refresh them before a
    # render. Here the ball moves far above the floor: a directional light's
    # shadow rays must now reach it (their length comes from the bounds).
    def scene(T):
        return mi.load_dict({
            "type": "scene",
            "integrator": {"type": "lg_direct"},
            "sensor": {"type": "perspective", "fov": 50,
                       "to_world": mi.ScalarTransform4f().look_at([0, -6, 4], [0, 0, 0],
                                                                  [0, 0, 1]),
                       "film": {"type": "hdrfilm", "width": 16, "height": 16,
                                "rfilter": {"type": "box"}},
                       "sampler": {"type": "independent", "sample_count": 2}},
            "sun": {"type": "directional", "direction": [0.0, 0.0, -1.0], "irradiance": 3.0},
            "sky": {"type": "constant", "radiance": 0.2},
            "floor": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale(3)},
            "s": {**BALL, "to_world": T}})
    high = mi.ScalarTransform4f().translate([0, 0, 20]).scale(2.5)
    moved = scene(mi.ScalarTransform4f().translate([2.5, 2.5, 1]).scale(0.3))
    render(moved)
    params = mi.traverse(moved)
    params["s.to_world"] = high
    params.update()
    fresh = render(scene(high))
    assert np.array_equal(render(moved), fresh)


def test_hand_given_L_refuses_updates_of_f():
    """A hand-given L bounds f for the loaded parameters only: an update of
    f's parameters is refused (it could break the guarantee) and the loaded
    value is put back; to_world still updates."""
    sc = mi.load_dict({"type": "scene", "s": {"type": "lgsurface", "surface": "torus",
                                              "L": 100.0}})
    p = mi.traverse(sc)
    p["s.R"] = 1.2
    with pytest.raises(Exception, match="hand-given L bounds f for the loaded parameters"):
        p.update()
    assert float(p["s.R"][0]) == 1.0
    p["s.to_world"] = mi.ScalarTransform4f().translate([0.5, 0, 0])
    p.update()
