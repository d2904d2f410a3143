"""What a new user meets first: bad sizes, a surface with nothing to hit,
which parameters are differentiable, errors through Mitsuba's loaders,
hints for unknown names, a variant change, the inverse-rendering example.

Oracles:
- the library's declaration of its sizes (``lgshape.surfaces.SIZES``, read
  from each function): every one refuses 0 and -1 at load and at
  ``params.update()`` with a message naming the surface, the parameter and
  the value, and every other numeric parameter accepts -1 (so the
  declaration is complete: no other parameter is refused as a size);
- closed forms for the empty surfaces: x^2 + y^2 + z^2 + 1 >= 1 everywhere;
  a unit sphere about (3, 0, 0) is at least 1 from the box [-1, 1]^3;
- lg_prb itself for the differentiable flags: each parameter that
  ``mi.traverse`` flags differentiable gets a finite forward-mode gradient
  image, each one it does not flag raises NotDifferentiableError;
- the op table (``lgshape.expr.ops.FUNCTIONS``) for the functions a hint
  lists; the message lgshape raises itself (``lgshape.parse``) for what the
  loaders report.
"""
import importlib.util
import inspect
import numbers
import pathlib
import subprocess
import sys
import textwrap
import warnings

import lgshape  # noqa: F401  (before mitsuba: sets up libLLVM)
import drjit as dr
import mitsuba as mi
import pytest

from lgshape.expr.ops import FUNCTIONS
from lgshape.primitives import COLUMNS
from lgshape.surfaces import LIBRARY, SIZES
from conftest import VARIANT

ROOT = pathlib.Path(__file__).parents[1]
BOX = {"bbox_min": [-1.0, -1.0, -1.0], "bbox_max": [1.0, 1.0, 1.0]}


@pytest.fixture(autouse=True)
def variant():
    mi.set_variant(VARIANT)
    lgshape.register_plugins()


def numeric(name):
    """A library surface's numeric parameters and their defaults."""
    return {p.name: float(p.default) for p in inspect.signature(LIBRARY[name]).parameters.values()
            if isinstance(p.default, numbers.Real)}


def load(shape, key="s"):
    return mi.load_dict({"type": "scene", key: shape})


# ---- Sizes ---------------------------------------------------------------

SIZE_CASES = [(name, p) for name in sorted(LIBRARY) for p in SIZES[name]]


def test01_library_declares_sizes():
    """Every declared size is a numeric parameter of its function, and the
    surfaces with a radius, half size or width declare one."""
    for name, sizes in SIZES.items():
        assert set(sizes) <= set(numeric(name)), name
    for name in LIBRARY:
        for p in numeric(name):
            if p in ("radius", "R", "r", "half_size", "width", "core"):
                assert p in SIZES[name], (name, p)


@pytest.mark.parametrize("name, param", SIZE_CASES)
@pytest.mark.parametrize("value", [0.0, -1.0])
def test02_size_refused_at_load(name, param, value):
    with pytest.raises(ValueError) as err:
        load({"type": "lgsurface", "surface": name, param: value})
    text = str(err.value)
    assert text.startswith(f"lgsurface: {name}: {param} must be > 0, got {value:g}"), text
    assert "bbox" not in text and "Traceback" not in text


@pytest.mark.parametrize("name, param", SIZE_CASES)
def test03_size_refused_at_update(name, param):
    scene = load({"type": "lgsurface", "surface": name}, key="obj")
    params = mi.traverse(scene)
    before = float(params[f"obj.{param}"][0])
    params[f"obj.{param}"] = 0.0
    with pytest.raises(ValueError, match=f"^lgsurface: {name}: {param} must be > 0, got 0"):
        params.update()
    assert float(params[f"obj.{param}"][0]) == before           # put back


@pytest.mark.parametrize("name, param", [(n, p) for n in sorted(LIBRARY) for p in numeric(n)
                                         if p not in SIZES[n]])
def test04_other_parameters_are_not_sizes(name, param):
    """-1 is no size error for a parameter that is not a size (it may leave
    nothing to hit: then a warning, not an error)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        load({"type": "lgsurface", "surface": name, param: -1.0})


@pytest.mark.parametrize("kind, column", [
    (kind, c) for kind, cols in COLUMNS.items() for c in cols if c in ("r", "R") or c[0] == "h"])
def test05_primitive_sizes_refused(tmp_path, kind, column):
    """A primitives file's radii and half sizes (its columns r, R, hx, hy,
    hz), each -0.5 in turn: refused, naming the kind, row and column."""
    good = {"cx": 0, "cy": 0, "cz": 0, "ax": 0, "ay": 0, "az": 0, "bx": 0.5, "by": 0, "bz": 0,
            "r": 0.2, "R": 0.6, "hx": 0.5, "hy": 0.5, "hz": 0.5, "rounding": 0}
    row = [(-0.5 if c == column else good[c]) for c in COLUMNS[kind]]
    path = tmp_path / "p.txt"
    path.write_text(f"{kind} " + " ".join(map(str, row)) + "\n")
    with pytest.raises(ValueError, match=f"{kind} 0: {column} must be positive, got -0.5"):
        load({"type": "lgsurface", "primitives": str(path)})


# ---- A surface with nothing to hit ----------------------------------------

def lg_warnings(caught):
    from lgshape.plugins import LGShapeWarning
    return [str(w.message) for w in caught if issubclass(w.category, LGShapeWarning)]


@pytest.mark.parametrize("expr", ["x^2 + y^2 + z^2 + 1", "(x - 3)^2 + y^2 + z^2 - 1"])
def test06_empty_surface_warned_once(expr):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        load({"type": "lgsurface", "expr": expr, **BOX}, key="ball")
    said = lg_warnings(caught)
    assert len(said) == 1, said
    assert said[0].startswith("lgsurface 'ball': f has no zero in its box (-1, -1, -1) .. "
                              "(1, 1, 1)")
    # no other warning for the same f (the library's own stands aside)
    assert len(caught) == 1, [str(w.message) for w in caught]


def test07_empty_after_update():
    """The unit sphere moved to x = 3 leaves the box: said once after the
    update that empties it, not again while it stays empty, never while
    the sphere is inside."""
    shape = {"type": "lgsurface", "expr": "(x - c)^2 + y^2 + z^2 - 1", "c": 0.0, **BOX}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        params = mi.traverse(load(shape, key="ball"))
        assert lg_warnings(caught) == []
        for c, expected in ((3.0, 1), (3.5, 1), (0.0, 1), (4.0, 2)):
            params["ball.c"] = c
            params.update()
            assert len(lg_warnings(caught)) == expected, c


# ---- Differentiable flags --------------------------------------------------

def prb_scene(name):
    """lg_prb at 8x8, 1 spp, without the silhouette term (its parameters
    go through the same differentiable forms as the interior's,
    ``LGSurface._ad_forms``)."""
    return mi.load_dict({
        "type": "scene", "integrator": {"type": "lg_prb", "max_depth": 2, "boundary": False},
        "sensor": {"type": "perspective", "fov": 50,
                   "to_world": mi.ScalarTransform4f().look_at([0.3, -6, 2], [0, 0, 0],
                                                              [0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": 8, "height": 8},
                   "sampler": {"type": "independent", "sample_count": 1}},
        "env": {"type": "constant"},
        "obj": {"type": "lgsurface", "surface": name}})


@pytest.mark.parametrize("name", sorted(LIBRARY))
def test08_flags_say_what_lg_prb_differentiates(name):
    """The flagged parameters of f, all with gradients at once: a finite
    forward gradient image; each unflagged one alone: NotDifferentiableError."""
    from lgshape.plugins import NotDifferentiableError
    scene = prb_scene(name)
    params = mi.traverse(scene)
    keys = [f"obj.{p}" for p in numeric(name)]
    flagged = [k for k in keys if not params.flags(k) & mi.ParamFlags.NonDifferentiable]
    for k in flagged:
        dr.enable_grad(params[k])
        dr.set_grad(params[k], 1.0)
    params.update()
    if flagged:
        grad = dr.forward_to(mi.render(scene, params, seed=1))
        assert dr.all(dr.isfinite(grad), axis=None)
    for k in flagged:
        dr.disable_grad(params[k])
    for k in (k for k in keys if k not in flagged):
        dr.enable_grad(params[k])
        dr.set_grad(params[k], 1.0)
        with pytest.raises(NotDifferentiableError, match=f"'{k}'"):
            dr.forward_to(mi.render(scene, params, seed=1))
        dr.disable_grad(params[k])


def test09_gyroid_half_size_not_differentiable():
    """The issue's case: the gyroid's half_size only sets its box."""
    params = mi.traverse(prb_scene("gyroid"))
    assert params.flags("obj.half_size") & mi.ParamFlags.NonDifferentiable
    assert not params.flags("obj.scale") & mi.ParamFlags.NonDifferentiable
    assert not params.flags("obj.to_world") & mi.ParamFlags.NonDifferentiable


# ---- Errors through Mitsuba's loaders -------------------------------------

BAD = "x^2 + sinn(y)"
XML = ('<scene version="3.0.0"><shape type="lgsurface" id="ball">'
       f'<string name="expr" value="{BAD}"/>'
       '<point name="bbox_min" value="-1,-1,-1"/><point name="bbox_max" value="1,1,1"/>'
       '</shape></scene>')


def parse_message():
    with pytest.raises(lgshape.ParseError) as err:
        lgshape.parse(BAD)
    return str(err.value).split("\n")[0]


def check_parse_error(err, where):
    text = str(err)
    assert isinstance(err, lgshape.ParseError) and isinstance(err, RuntimeError)
    assert "Traceback" not in text and "parser.cpp" not in text and 'File "' not in text
    assert text.startswith(f"lgsurface: malformed 'expr': {parse_message()}"), text
    assert err.pos == BAD.index("sinn") and err.identifier == "sinn"
    assert text.endswith(f"\n  at {where}"), text


def test10_parse_error_through_load_dict():
    try:
        mi.load_dict({"type": "scene", "ball": {"type": "lgsurface", "expr": BAD, **BOX}})
    except lgshape.ParseError as err:
        check_parse_error(err, 'dictionary node "ball"')
    else:
        pytest.fail("no ParseError")


def test11_parse_error_through_load_string_and_file(tmp_path):
    try:
        mi.load_string(XML)
    except lgshape.ParseError as err:
        check_parse_error(err, "string (line 1, col 25)")
    else:
        pytest.fail("no ParseError")
    path = tmp_path / "bad.xml"
    path.write_text(XML)
    with pytest.raises(lgshape.ParseError) as err:
        mi.load_file(str(path))
    check_parse_error(err.value, f"{path} (line 1, col 25)")


def test12_other_errors_keep_mitsubas_own():
    """A Mitsuba error (an unknown plugin) stays Mitsuba's RuntimeError."""
    with pytest.raises(RuntimeError, match="doughnut") as err:
        mi.load_dict({"type": "scene", "s": {"type": "doughnut"}})
    assert type(err.value) is RuntimeError


# ---- Hints ------------------------------------------------------------------

def test13_unknown_function_hint():
    with pytest.raises(lgshape.ParseError) as err:
        load({"type": "lgsurface", "expr": "tan(x) - y", **BOX})
    text = str(err.value)
    assert f"'tan' is not a function of the expression language; its functions are " \
           f"{', '.join(FUNCTIONS)}" in text
    assert "named constant" not in text
    with pytest.raises(lgshape.ParseError, match=r"did you mean 'sin'\?"):
        load({"type": "lgsurface", "expr": "sinn(x) - y", **BOX})


def test14_named_constant_hint():
    with pytest.raises(lgshape.ParseError) as err:
        load({"type": "lgsurface", "expr": "x^2 + y^2 + z^2 - radius^2", "radious": 1.0, **BOX})
    text = str(err.value)
    assert '<float name="radius" value="1"/>' in text
    assert "the shape has a property 'radious'" in text


@pytest.mark.parametrize("props", [
    {"grid": 3},
    {"surface": "sphere", "grid": 3},
    {"expr": "x - 1", **BOX, "grid": 3},
    {"expr": "x - 1", "grid": 3},              # (no box: another error first)
    {"surface": "doughnut", "grid": 3},
])
def test15_unknown_keys_always_named(props):
    with pytest.raises(ValueError, match="unknown parameter 'grid'"):
        load({"type": "lgsurface", **props})


@pytest.mark.parametrize("props, message", [
    ({"expr": 3}, "'expr' must be a string"),
    ({"expr": "x - 1", "bbox_min": "abc", "bbox_max": [1, 1, 1]},
     "'bbox_min' must be a point"),
    ({"expr": "x - 1", "bbox_min": [-1, -1, -1], "bbox_max": [1, 1, float("inf")]},
     "the box must be finite"),
    ({"expr": "x - 1", **BOX, "smoothness": 0.1}, "'smoothness' does not apply here"),
    ({"surface": "sphere", "threshold": 0.3}, "'threshold' does not apply here"),
    ({"surface": "sphere", "combine": "blend"}, "'combine' does not apply here"),
], ids=["expr_int", "bbox_text", "bbox_inf", "smoothness_with_expr", "threshold_with_surface",
        "combine_with_surface"])
def test15b_property_errors_name_the_property(props, message):
    """Cases the fuzz test (test_20) met: each error names the property."""
    with pytest.raises(ValueError, match=message):
        load({"type": "lgsurface", **props})


# ---- A variant change -------------------------------------------------------

def test16_variant_change_needs_no_second_registration():
    """register_plugins() once; then mono, spectral and back to rgb load
    and render an lgsurface (in a fresh process: variants are global)."""
    code = textwrap.dedent("""
        import lgshape, mitsuba as mi, numpy as np
        mi.set_variant("llvm_ad_rgb")
        lgshape.register_plugins()
        for v in ("llvm_ad_mono", "llvm_ad_spectral", "llvm_ad_rgb"):
            mi.set_variant(v)
            scene = mi.load_dict({"type": "scene", "integrator": {"type": "lg_aov",
                                  "aovs": "d:depth"},
                                  "sensor": {"type": "perspective", "film": {"type": "hdrfilm",
                                             "width": 4, "height": 4}, "to_world":
                                             mi.ScalarTransform4f().look_at([0, 0, 4],
                                                                            [0, 0, 0], [0, 1, 0])},
                                  "s": {"type": "lgsurface", "surface": "sphere"}})
            depth = np.array(mi.render(scene))[..., -1]
            print("RESULT", v, type(scene.shapes()[0]).__name__, float(depth[2, 2]))
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-3000:]
    lines = [ln.split("RESULT ")[1].split() for ln in out.stdout.splitlines() if "RESULT " in ln]
    assert len(lines) == 3, out.stdout
    for (name, cls, depth), v in zip(lines, ("llvm_ad_mono", "llvm_ad_spectral", "llvm_ad_rgb")):
        assert (name, cls) == (v, "LGSurface")
        # the ray through a pixel near the centre meets the unit sphere
        # at a distance between 4 - 1 and the camera's distance 4
        assert 3.0 <= float(depth) < 4.0


# ---- The example's options and verdict ---------------------------------------

def example():
    spec = importlib.util.spec_from_file_location("inverse_rendering",
                                                  ROOT / "examples" / "inverse_rendering.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test17_example_help_shows_defaults():
    text = example().parser().format_help()
    for option, default in (("--iterations", 200), ("--res", 48), ("--spp", 16),
                            ("--tolerance", 0.01)):
        assert option in text and f"(default: {default})" in text, option
    assert "--lr" in text and "(default: the problem's" in text
    assert "32 x --spp" in text and "Exit status: 0 converged" in " ".join(text.split())


def test18_example_verdict():
    verdict = example().verdict
    text, status = verdict({"obj.R": 0.004, "obj.r": 0.009}, 0.01, "relative errors", 200)
    assert status == 0 and text.startswith("converged")
    text, status = verdict({"obj.R": 0.004, "obj.r": 0.023}, 0.01, "relative errors", 20)
    assert status == 1 and text.startswith("did not converge")
    assert "obj.r is off by 2.30%" in text and "obj.R" not in text
