"""Nothing silent (:mod:`lgshape.plugins.checks`): an integrator that cannot
see a scene's lgsurfaces, media that the lg integrators ignore and
gradients on lgsurface parameters are reported; ``mi.traverse`` lists only
the surface's own parameters (and its BSDF's).

Oracles: the plugin names as the scene gives them (``"type": "path"``) and
the lg integrator the README names for each; the shapes' ids as the scene
gives them; the parameter list that ``lgsurface``'s docstring documents; a
render before an update refused, at the same seed with one sample per pixel
and a box filter (each pixel one sample: bit for bit); for the BSDF's
gradient, the same-seed finite difference of an image that is linear in
the reflectance.
"""
import warnings

import lgshape  # noqa: F401  (before mitsuba: sets up libLLVM)
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from conftest import VARIANT

from lgshape import cli


@pytest.fixture(autouse=True)
def variant():
    mi.set_variant(VARIANT)
    lgshape.register_plugins()


def checks():
    from lgshape.plugins import checks
    return checks


BALL = {"type": "lgsurface", "expr": "x^2 + y^2 + z^2 - radius^2", "radius": 1.0,
        "bbox_min": [-1.1] * 3, "bbox_max": [1.1] * 3, "bsdf": {"type": "diffuse"}}


def scene(integrator, spp=1, **shapes):
    shapes = {"ball": BALL} if not shapes else shapes
    return mi.load_dict({
        "type": "scene", "integrator": integrator,
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at([0, -4, 0], [0, 0, 0], [0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": 6, "height": 6,
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "env": {"type": "constant"}, **shapes})


def lg_warnings(fn):
    """Run fn() with every LGShapeWarning recorded; return their messages."""
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        fn()
    return [str(w.message) for w in seen if issubclass(w.category, checks().LGShapeWarning)]


# ---------------------------------------------------------------------------
#  Integrators that cannot see lgsurfaces
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("plugin, instead", [
    ("path", "lg_path"), ("volpath", "lg_volpath"), ("volpathmis", "lg_volpath"),
    ("prb", "lg_prb"), ("prbvolpath", "lg_volpath"), ("direct", "lg_direct"), ("aov", "lg_aov"),
    ("depth", "lg_aov")])
def test01_mitsuba_integrator_warns_through_mi_render(plugin, instead):
    # Oracle: the plugin as the scene names it, the README's lg counterpart,
    # the lgsurface's id; once for two renders of the same scene.
    props = {"type": plugin, **({"aovs": "dd:depth"} if plugin == "aov" else {})}
    s = scene(props)
    said = lg_warnings(lambda: (mi.render(s), mi.render(s, spp=1, seed=1)))
    assert len(said) == 1, said
    assert f"the integrator '{plugin}' does not see lgsurface shapes" in said[0]
    assert f"use '{instead}' instead" in said[0] and "'ball'" in said[0]
    for cpp_class in ("MonteCarloIntegrator", "SamplingIntegrator", "Integrator'"):
        assert cpp_class not in said[0]
    # another scene: said again (once per scene)
    assert len(lg_warnings(lambda: mi.render(scene(props)))) == 1


@pytest.mark.parametrize("plugin", ["lg_path", "lg_direct", "lg_aov"])
def test02_lg_integrators_are_quiet(plugin):
    # Oracle: an lg integrator sees the lgsurfaces; no medium in the scene.
    props = {"type": plugin, **({"aovs": "dd:depth"} if plugin == "lg_aov" else {})}
    assert lg_warnings(lambda: mi.render(scene(props))) == []


def test03_native_integrator_nested_in_lg_aov():
    # Oracle: lg_aov's AOVs see the lgsurfaces, its nested `path` does not.
    s = scene({"type": "lg_aov", "aovs": "dd:depth", "image": {"type": "path"}})
    said = lg_warnings(lambda: mi.render(s))
    assert len(said) == 1
    assert "the integrator 'path' nested in lg_aov does not see lgsurface" in said[0]
    assert "nest 'lg_path' instead" in said[0]


def test04_no_lgsurface_no_warning():
    # Oracle: a native-only scene renders fine with Mitsuba's path.
    s = scene({"type": "path"}, cube={"type": "cube"})
    assert lg_warnings(lambda: mi.render(s)) == []


def tiny_scene(integrator, shape):
    """A scene file for the command line: a 4 x 4 image at 1 spp."""
    return f"""<scene version="3.0.0">
    {integrator}
    <sensor type="perspective"><film type="hdrfilm"><integer name="width" value="4"/>
        <integer name="height" value="4"/></film>
        <sampler type="independent"><integer name="sample_count" value="1"/></sampler></sensor>
    {shape}
</scene>"""


def test05_command_line_names_the_plugin(tmp_path, capsys):
    # Oracle: the scene's <integrator type="prb"/>; one warning line.
    xml = tmp_path / "prb.xml"
    xml.write_text(tiny_scene('<integrator type="prb"/>',
                              '<shape type="lgsurface" id="knot"><string name="surface" value="torus"/></shape>'))
    assert cli.main(["render", str(xml), "-o", str(tmp_path / "x.png")]) == 0
    lines = [ln for ln in capsys.readouterr().err.splitlines() if "warning" in ln]
    assert len(lines) == 1, lines
    assert lines[0].startswith("lgshape: warning: the integrator 'prb' does not see lgsurface")
    assert "'knot'" in lines[0] and "use 'lg_prb' instead" in lines[0]


# ---------------------------------------------------------------------------
#  Media that the lg integrators ignore
# ---------------------------------------------------------------------------

FOG = {"type": "homogeneous", "sigma_t": 0.5}


@pytest.mark.parametrize("plugin", ["lg_path", "lg_direct", "lg_aov"])
def test06_medium_on_a_native_shape(plugin):
    # Oracle: the shape's id; a native-only scene is Mitsuba volpath's.
    props = {"type": plugin, **({"aovs": "dd:depth"} if plugin == "lg_aov" else {})}
    s = scene(props, fogbox={"type": "cube", "bsdf": {"type": "null"}, "interior": FOG})
    said = lg_warnings(lambda: (mi.render(s), s.integrator().render(s, s.sensors()[0])))
    assert len(said) == 1, said
    assert said[0].startswith(f"{plugin} ignores participating media")
    assert "the shape 'fogbox' (Cube) has an interior medium" in said[0]
    assert "render it with Mitsuba's 'volpath'" in said[0]


def test07_medium_on_an_lgsurface_and_on_the_sensor():
    # Oracle: the ids of the shape and of the sensor that carry the media;
    # with lgsurfaces, lg_volpath renders both.
    s = mi.load_dict({
        "type": "scene", "integrator": {"type": "lg_path"},
        "cam": {"type": "perspective", "medium": FOG,
                "film": {"type": "hdrfilm", "width": 4, "height": 4}},
        "glass": {**BALL, "exterior": FOG}, "other": {"type": "lgsurface", "surface": "torus"}})
    said = lg_warnings(lambda: mi.render(s, spp=1))
    assert len(said) == 1, said
    assert "the shape 'glass' (lgsurface) has an exterior medium" in said[0]
    assert "the sensor 'cam' is in the medium" in said[0]
    assert "render it with 'lg_volpath'" in said[0] and "'other'" not in said[0]


def test08_volpath_on_media_without_lgsurfaces_is_quiet():
    # Oracle: Mitsuba's volpath renders media and sees every native shape.
    s = scene({"type": "volpath"}, fogbox={"type": "cube", "bsdf": {"type": "null"},
                                           "interior": FOG})
    assert lg_warnings(lambda: mi.render(s)) == []


def test09_command_line_reports_media(tmp_path, capsys):
    # Oracle: the medium's shape id in the scene file, one warning line.
    xml = tmp_path / "fog.xml"
    xml.write_text(tiny_scene('<integrator type="lg_path"/>',
                              '<shape type="sphere" id="cloud"><bsdf type="null"/>'
                              '<medium type="homogeneous" name="interior"/></shape>'))
    assert cli.main(["render", str(xml), "-o", str(tmp_path / "x.png")]) == 0
    lines = [ln for ln in capsys.readouterr().err.splitlines() if "warning" in ln]
    assert len(lines) == 1, lines
    assert lines[0].startswith("lgshape: warning: lg_path ignores participating media, but "
                               "the shape 'cloud' (Sphere) has an interior medium")


# ---------------------------------------------------------------------------
#  mi.traverse and gradients
# ---------------------------------------------------------------------------

def test10_traverse_lists_the_surface_parameters_only():
    # Oracle: lgsurface's docstring: to_world, f's parameters
    # (differentiable and discontinuous, as Mitsuba flags geometry), the
    # BSDF's and media's (Mitsuba's flags); not the placeholder triangle's.
    s = scene({"type": "lg_path"}, ball={**BALL, "interior": FOG})
    params = mi.traverse(s)
    mine = sorted(k for k in params.keys() if k.startswith("ball."))
    assert mine == ["ball.bsdf.reflectance.value", "ball.interior_medium.albedo.value.value",
                    "ball.interior_medium.scale", "ball.interior_medium.sigma_t.value.value",
                    "ball.radius", "ball.to_world"]
    for k in ("ball.radius", "ball.to_world"):
        assert not params.flags(k) & mi.ParamFlags.NonDifferentiable
        assert params.flags(k) & mi.ParamFlags.Discontinuous
    assert not params.flags("ball.bsdf.reflectance.value") & mi.ParamFlags.NonDifferentiable


@pytest.mark.parametrize("key", ["ball.radius", "ball.to_world"])
def test11_gradient_on_an_lgsurface_parameter_needs_lg_prb(key):
    # Oracle: the message names the key and lg_prb; the update keeps the
    # values, so the render after the gradient is disabled is the one
    # before, bit for bit (one sample per pixel, box filter: no sums whose
    # order could vary).
    s = scene({"type": "lg_path", "max_depth": 3})
    before = np.array(mi.render(s, seed=3))
    params = mi.traverse(s)
    dr.enable_grad(params[key])
    params.update()
    # (try/except, not pytest.raises: an ExceptionInfo would keep this scene
    # in a reference cycle, and a garbage collection of a scene in the middle
    # of the next test's kernel tracing aborts Dr.Jit 1.5 with "invalid
    # redefinition of function" in the LLVM IR of its shape calls)
    NotDifferentiable = checks().NotDifferentiableError
    message = refused(lambda: mi.render(s, params, seed=3), NotDifferentiable)
    assert f"'{key}'" in message and "'lg_path'" in message and "'lg_prb'" in message
    dr.disable_grad(params[key])
    assert np.array_equal(np.array(mi.render(s, seed=3)), before)


def refused(fn, error):
    """The message of the `error` that fn() raises (none raised: a failure)."""
    try:
        fn()
    except error as err:
        return str(err)
    raise AssertionError(f"{fn} did not raise {error.__name__}")


def test12_bsdf_parameter_is_differentiable():
    """The gradient of the mean image with respect to the ball's diffuse
    reflectance rho, by mi.render's AD through lg_path, equals the finite
    difference at the seed of its differential pass (``seed_grad``: the
    primal ``seed`` only gives the image). Oracle: with max_depth 2 (direct light from a constant
    environment) and no Russian roulette, each sample's value is
    rho A + B with A, B independent of rho, so (I(rho1) - I(rho0)) /
    (rho1 - rho0) is the derivative up to rounding. Bound: each pixel of a
    render is within gamma_K of its exact value, K = 200 float32 roundings
    for one sample's estimate (ray, hit, BSDF and emitter sampling and
    evaluation, MIS weights, throughput, film; an upper count) plus the 4
    samples' sum; so the difference quotient is within gamma_K (I1 + I0) /
    (rho1 - rho0) and the AD gradient within gamma_K |g|."""
    s = scene({"type": "lg_path", "max_depth": 2}, spp=4)
    params = mi.traverse(s)
    key = "ball.bsdf.reflectance.value"

    def mean_image(rho):
        params[key] = rho
        params.update()
        return float(np.mean(np.array(mi.render(s, seed=11), np.float64)))

    I0, I1 = mean_image(0.25), mean_image(0.75)
    params[key] = 0.5
    params.update()
    dr.enable_grad(params[key])
    img = mi.render(s, params, seed=7, seed_grad=11)
    dr.backward(dr.mean(img, axis=None))
    g = float(dr.grad(params[key])[0])
    k = 204 * 2.0 ** -24
    gamma = k / (1 - k)
    fd = (I1 - I0) / 0.5
    assert g > 0.05
    assert abs(g - fd) <= gamma * (I1 + I0) / 0.5 + gamma * abs(g), (g, fd)
