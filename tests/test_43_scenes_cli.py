"""The scenes in ``scenes/`` and the ``lgshape`` command line.

Oracles: every scene renders through the command line at a tiny size (set
with ``-D``, as the README promises) to finite, non-black images of that
size, which change where its lgsurfaces are taken out; the EXR's channel
names are read back with the OpenEXR package (not with Mitsuba, which wrote
them); bad input gives ``lgshape: error:`` naming the culprit, exit status 2,
no traceback and no file, before anything is loaded or rendered where the
output is at fault; ``--spp`` is checked by the Monte Carlo error (its
variance falls as 1/spp), and where an lgsurface is drawn by a float64
ray-sphere oracle on Mitsuba's own camera rays.
"""
import os
import pathlib
import shutil
import subprocess
import sys
import time
import xml.etree.ElementTree as ET

import lgshape  # noqa: F401  (before mitsuba: sets up libLLVM)
import mitsuba as mi
import numpy as np
import OpenEXR
import pytest
from conftest import sensor_xml

from lgshape import cli, render
from conftest import VARIANT

SCENES = sorted((pathlib.Path(__file__).parent.parent / "scenes").glob("*.xml"))
#: A small render for the CLI tests (16x12, 2 spp).
SMALL = ["-D", "resx=16", "-D", "resy=12", "-D", "spp=2"]

AOV_SCENE = """<scene version="3.0.0">
    <default name="resx" value="12"/>
    <default name="resy" value="10"/>
    <default name="fov" value="40"/>
    <integrator type="lg_aov">
        <string name="aovs" value="dd.y:depth,nn:sh_normal"/>
        {nested}
    </integrator>
    """ + sensor_xml("0, 0, 7", fov="$fov", width="$resx", height="$resy", spp=2) + """
    <shape type="lgsurface"><string name="surface" value="torus"/></shape>
    <emitter type="constant"/>
</scene>
"""

# A unit sphere given as an expression, scaled and moved off the axis, in
# front of a native rectangle that fills the view, under a constant sky:
# depth along every camera ray has a closed form (SPHERE_C, SPHERE_R, PLANE_Z).
SPHERE_C, SPHERE_R, PLANE_Z = np.array([0.25, -0.15, 0.1]), 0.8, -1.0
SPHERE_SCENE = """<scene version="3.0.0">
    <default name="spp" value="4"/>
    <default name="res" value="24"/>
    <integrator type="lg_aov">
        <string name="aovs" value="dd:depth"/>
        <integrator type="lg_path" name="image"><integer name="max_depth" value="3"/></integrator>
    </integrator>
    """ + sensor_xml("0, 0, 5", fov="30") + """
    <emitter type="constant"/>
    <shape type="rectangle">
        <transform name="to_world"><scale value="3"/><translate z="-1"/></transform>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.3, 0.5, 0.7"/></bsdf>
    </shape>
    <shape type="lgsurface">
        <string name="expr" value="x^2 + y^2 + z^2 - 1"/>
        <point name="bbox_min" value="-1.2, -1.2, -1.2"/>
        <point name="bbox_max" value="1.2, 1.2, 1.2"/>
        <transform name="to_world"><scale value="0.8"/><translate x="0.25" y="-0.15" z="0.1"/></transform>
        <bsdf type="diffuse"/>
    </shape>
</scene>
"""


@pytest.fixture(autouse=True)
def variant(monkeypatch):
    mi.set_variant(VARIANT)
    lgshape.register_plugins()
    monkeypatch.setattr(cli, "DEFAULT_VARIANT", VARIANT)    # in-process `lgshape render`


def read_exr(path):
    with OpenEXR.File(str(path)) as f:
        return {name: np.asarray(ch.pixels) for name, ch in f.channels().items()}


def test01_scenes_exist():
    # Oracle: the list (a Cornell showcase, one scene per class of
    # library surface, one mixed scene).
    names = {p.stem for p in SCENES}
    assert {"cornell", "algebraic", "soft", "periodic", "spikes", "mixed"} <= names


def scene_copy(scene, path, lgsurfaces=True, depth_aov=False):
    """A copy of the scene file: without its top-level lgsurface shapes
    unless `lgsurfaces`; with `depth_aov`, its integrator nested in an lg_aov
    that adds the depth channel "dd.T"."""
    tree = ET.parse(scene)
    root = tree.getroot()
    if depth_aov:
        integrator = root.find("integrator")
        at = list(root).index(integrator)
        root.remove(integrator)
        integrator.set("name", "image")
        aov = ET.Element("integrator", type="lg_aov")
        ET.SubElement(aov, "string", name="aovs", value="dd:depth")
        aov.append(integrator)
        root.insert(at, aov)
    if not lgsurfaces:
        shapes = [e for e in root if e.tag == "shape" and e.get("type") == "lgsurface"]
        assert shapes
        for e in shapes:
            root.remove(e)
    tree.write(path)
    data = scene.parent / "data"            # files the scene refers to (primitives)
    if data.is_dir() and not (path.parent / "data").exists():
        shutil.copytree(data, path.parent / "data")
    return path


@pytest.mark.parametrize("scene", SCENES, ids=lambda p: p.stem)
def test02_scene_renders_tiny(scene, tmp_path):
    # Oracle: a 16x12 image with finite values that is not black, and a PNG
    # beside the EXR; every scene declares the spp/resx/resy defaults.
    text = scene.read_text()
    for name in ("spp", "resx", "resy"):
        assert f'<default name="{name}"' in text
    out = tmp_path / f"{scene.stem}.exr"
    assert cli.main(["render", str(scene), "-o", str(out), *SMALL]) == 0
    rgb = read_exr(out)["RGB"]
    assert rgb.shape == (12, 16, 3)
    assert np.all(np.isfinite(rgb)) and rgb.mean() > 0.01
    assert (tmp_path / f"{scene.stem}.png").stat().st_size > 0


@pytest.mark.parametrize("scene", SCENES, ids=lambda p: p.stem)
def test02b_scene_lgsurfaces_are_drawn(scene, tmp_path):
    # Oracle: the scene, its integrator wrapped in an lg_aov with a depth
    # channel, against the same without its lgsurfaces (same seeds, so the
    # same camera rays): where an lgsurface is seen, the depth changes, in
    # at least 20% of the 16x12 pixels (each scene's lgsurfaces cover 33% or
    # more); the colour changes by more than 0.05 in at least 10% (17% or
    # more). Were the lgsurfaces not drawn, the images would be identical;
    # were they only invisible to camera rays, the depths would be.
    ch = {}
    for kind in ("keep", "bare"):
        path = scene_copy(scene, tmp_path / f"{kind}.xml", lgsurfaces=kind == "keep",
                          depth_aov=True)
        assert cli.main(["render", str(path), "-o", str(tmp_path / f"{kind}.exr"), *SMALL]) == 0
        ch[kind] = read_exr(tmp_path / f"{kind}.exr")
    d_keep, d_bare = ch["keep"]["dd.T"], ch["bare"]["dd.T"]
    changed = np.abs(d_keep - d_bare) > 1e-3 * np.maximum(d_keep, d_bare)
    assert changed.mean() >= 0.20
    assert (np.abs(ch["keep"]["RGB"] - ch["bare"]["RGB"]).max(-1) > 0.05).mean() >= 0.10


def test03_aov_channels_in_exr(tmp_path):
    # Oracle: the EXR read back has the AOV channels under their names, and
    # depth is positive exactly where the normal is non-zero (a pixel with any
    # sample on the torus).
    scene = tmp_path / "aov.xml"
    scene.write_text(AOV_SCENE.format(nested='<integrator type="lg_path" name="image"/>'))
    out = tmp_path / "aov.exr"
    assert cli.main(["render", str(scene), "-o", str(out), "--spp", "3"]) == 0
    ch = read_exr(out)
    assert {"RGB", "dd.y.T", "nn.X", "nn.Y", "nn.Z"} <= set(ch)
    depth = ch["dd.y.T"]
    normal = np.stack([ch["nn." + a] for a in "XYZ"], -1)
    assert depth.shape == (10, 12) and (depth > 0).any() and (depth == 0).any()
    assert np.array_equal(depth > 0, np.linalg.norm(normal, axis=-1) > 0)
    assert ch["RGB"].mean() > 0


def test04_png_only(tmp_path):
    # Oracle: -o x.png writes x.png and nothing else; without a nested
    # integrator the preview shows the first AOV (not a black image).
    scene = tmp_path / "aov.xml"
    scene.write_text(AOV_SCENE.format(nested=""))
    assert cli.main(["render", str(scene), "-o", str(tmp_path / "depth.png")]) == 0
    assert sorted(os.listdir(tmp_path)) == ["aov.xml", "depth.png"]
    png = np.array(mi.Bitmap(str(tmp_path / "depth.png")))
    assert png.shape[:2] == (10, 12) and png.max() > 0


def test05_defines_and_spp(tmp_path):
    # Oracle: -D overrides a <default>, --spp overrides the sampler.
    scene = tmp_path / "aov.xml"
    scene.write_text(AOV_SCENE.format(nested=""))
    out = tmp_path / "a.exr"
    assert cli.main(["render", str(scene), "-o", str(out), "-D", "resx=7", "--spp", "1"]) == 0
    assert read_exr(out)["dd.y.T"].shape == (10, 7)


BAD_INPUT = [
    # (extra arguments, what stderr must say after "lgshape: error:")
    (["-D", "resx"], ["-D expects name=value, got 'resx'"]),
    (["-D", "resx=0"], ["-D resx=0", "'resx' must be at least 1", "width"]),
    (["-D", "resy=-2"], ["-D resy=-2", "'resy' must be at least 1", "height"]),
    (["-D", "resx=abc"], ["-D resx=abc", "'resx' must be an integer", "width"]),
    (["-D", "resx=1.5"], ["-D resx=1.5", "'resx' must be an integer"]),
    (["-D", "fov=wide"], ["-D fov=wide", "'fov' must be a number", "fov"]),
    (["-D", "nope=3"], ["-D nope=3", "no parameter 'nope'", "fov, resx, resy"]),
    (["--spp", "0"], ["--spp must be at least 1"]),
    (["--variant", "scalar_rgb"], ["'scalar_rgb' is a scalar variant"]),
    (["--variant", "llvm_rgb_nope"], ["unknown variant 'llvm_rgb_nope'"]),
    (["-o", "x.jpg"], ["-o x.jpg", "the output must end in .exr or .png"]),
]


@pytest.mark.parametrize("args, messages", BAD_INPUT, ids=[" ".join(a) for a, _ in BAD_INPUT])
def test06_errors(tmp_path, capsys, monkeypatch, args, messages):
    # Oracle: exit status 2, "lgshape: error:" and the message naming the
    # option or -D parameter on stderr, no traceback, no file written (the
    # folder holds only the scene; output goes to the current folder).
    scene = tmp_path / "aov.xml"
    scene.write_text(AOV_SCENE.format(nested=""))
    monkeypatch.chdir(tmp_path)
    assert cli.main(["render", str(scene), *args]) == 2
    err = capsys.readouterr().err
    assert err.startswith("lgshape: error:") and "Traceback" not in err
    for message in messages:
        assert message in err
    assert os.listdir(tmp_path) == ["aov.xml"]


def test06b_spp_default_checked(tmp_path, capsys):
    # Oracle: Mitsuba rejects -D spp=-3 only as "sample_count out of bounds"
    # and loads spp=0, then fails while rendering; the command line names spp.
    for value in ("-3", "0"):
        out = tmp_path / "x.exr"
        assert cli.main(["render", str(SCENES[0]), "-o", str(out), "-D", f"spp={value}"]) == 2
        err = capsys.readouterr().err
        assert f"-D spp={value}: 'spp' must be at least 1" in err and "sample_count" in err
        assert os.listdir(tmp_path) == []


def _bad_outputs(tmp_path):
    (tmp_path / "file").write_text("")
    (tmp_path / "dir.exr").mkdir()
    return {
        "missing-folder": (tmp_path / "missing" / "x.exr", "does not exist"),
        "folder-is-a-file": (tmp_path / "file" / "x.exr", "is not a folder"),
        "output-is-a-folder": (tmp_path / "dir.exr", "is a folder"),
    }


@pytest.mark.parametrize("case", ["missing-folder", "folder-is-a-file", "output-is-a-folder",
                                  "read-only-folder"])
def test10_bad_output_found_before_rendering(tmp_path, capsys, monkeypatch, case):
    # Oracle: the output is checked before the scene is loaded: Mitsuba's
    # loader and the render passes are replaced by traps that fail the test;
    # exit status 2, the message names -o and the reason; no file is left.
    if case == "read-only-folder":
        folder = tmp_path / "ro"
        folder.mkdir()
        folder.chmod(0o555)
        if os.access(folder, os.W_OK):
            pytest.skip("running as root: a read-only folder is still writable")
        out, reason = folder / "x.exr", "cannot write to the output folder"
    else:
        out, reason = _bad_outputs(tmp_path)[case]
    before = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*"))

    def trap(*args, **kwargs):
        raise AssertionError("the scene was loaded or rendered")
    monkeypatch.setattr(mi, "load_file", trap)
    monkeypatch.setattr(render, "render_passes", trap)
    assert cli.main(["render", str(SCENES[0]), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"lgshape: error: -o {out}:") and reason in err
    assert "Traceback" not in err and err.count("\n") == 1
    assert sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*")) == before


def test11_bad_output_is_quick_from_the_shell(tmp_path):
    # Oracle: the same from a fresh process, with a scene set to take many
    # minutes (2048x2048 at 1024 spp): the command ends within 60 s (start-up
    # included), with one error line and no progress or "rendered" line.
    cmd = [sys.executable, "-m", "lgshape.cli", "render", str(SCENES[0]),
           "-o", str(tmp_path / "missing" / "x.exr"),
           "-D", "resx=2048", "-D", "resy=2048", "-D", "spp=1024"]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    seconds = time.perf_counter() - t0
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.splitlines() == [
        f"lgshape: error: -o {tmp_path / 'missing' / 'x.exr'}: the output folder "
        f"{tmp_path / 'missing'} does not exist"]
    assert seconds < 60
    assert os.listdir(tmp_path) == []


BROKEN_SCENES = {
    # name: (edit of AOV_SCENE, what stderr must say)
    "malformed-xml": (lambda t: t.replace("</sensor>", "</sensr>"),
                      ["cannot load", "Start-end tags mismatch"]),
    "unknown-surface": (lambda t: t.replace('value="torus"', 'value="tours"'),
                        ["cannot load", "lgsurface: unknown surface 'tours'"]),
    "malformed-expr": (lambda t: t.replace('<string name="surface" value="torus"/>',
                                           '<string name="expr" value="x^2 + * y"/>'
                                           '<point name="bbox_min" value="-1, -1, -1"/>'
                                           '<point name="bbox_max" value="1, 1, 1"/>'),
                       ["lgsurface: malformed 'expr'", "at position 7"]),
    "bad-size": (lambda t: t.replace('value="torus"/>', 'value="torus"/><float name="r" '
                                                          'value="-0.2"/>'),
                 ["lgsurface: torus: r must be > 0, got -0.2", "bad.xml (line "]),
    "unknown-key": (lambda t: t.replace('value="torus"/>', 'value="torus"/><integer '
                                                          'name="grid" value="3"/>'),
                    ["lgsurface: unknown parameter 'grid'"]),
    "bad-aov": (lambda t: t.replace("dd.y:depth", "dd.y:deep"),
                ["lg_aov: unknown AOV type 'deep'"]),
    "no-sensor": (lambda t: t[:t.index("<sensor")] + t[t.index("</sensor>") + 9:],
                  ["has no <sensor>"]),
    "not-a-scene": (lambda t: '<integrator type="lg_path" version="3.0.0"/>',
                    ["is not a scene"]),
}


@pytest.mark.parametrize("case", sorted(BROKEN_SCENES))
def test12_broken_scene(tmp_path, capsys, case):
    # Oracle: Mitsuba's or lgshape's own message after "lgshape: error:",
    # exit status 2, without the Python traceback that Mitsuba puts in the
    # error of a Python plugin, and no file written.
    edit, messages = BROKEN_SCENES[case]
    scene = tmp_path / "bad.xml"
    scene.write_text(edit(AOV_SCENE.format(nested="")))
    assert cli.main(["render", str(scene), "-o", str(tmp_path / "x.exr")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("lgshape: error:") and "Traceback" not in err, err
    assert 'File "' not in err
    for message in messages:
        assert message in err
    assert os.listdir(tmp_path) == ["bad.xml"]


def test13_plugin_error_from_a_define(tmp_path, capsys):
    # Oracle: lg_path's own message, and the -D that caused it.
    scene = next(p for p in SCENES if p.stem == "cornell")
    assert cli.main(["render", str(scene), "-o", str(tmp_path / "x.exr"),
                     "-D", "max_depth=-5"]) == 2
    err = capsys.readouterr().err
    assert "lg_path: 'max_depth' must be -1 (no limit) or >= 0" in err
    assert "-D max_depth=-5" in err and "Traceback" not in err
    assert os.listdir(tmp_path) == []


def test12b_empty_surface_warned(tmp_path, capsys):
    # Oracle: f = x^2 + y^2 + z^2 + 1 >= 1 has no zero: the command says so
    # once, as its own warning, and renders.
    scene = tmp_path / "empty.xml"
    scene.write_text(AOV_SCENE.format(nested="").replace(
        '<shape type="lgsurface">', '<shape type="lgsurface" id="ball">').replace(
        '<string name="surface" value="torus"/>',
        '<string name="expr" value="x^2 + y^2 + z^2 + 1"/>'
        '<point name="bbox_min" value="-1, -1, -1"/><point name="bbox_max" value="1, 1, 1"/>'))
    assert cli.main(["render", str(scene), "-o", str(tmp_path / "x.png")]) == 0
    err = capsys.readouterr().err
    assert err.count("lgshape: warning: lgsurface 'ball': f has no zero in its box") == 1, err


def test07_missing_scene_and_bad_plugin(tmp_path, capsys):
    # Oracle: the messages name the file and the lgsurface problem.
    assert cli.main(["render", str(tmp_path / "none.xml")]) == 2
    assert "no such scene file" in capsys.readouterr().err
    scene = tmp_path / "bad.xml"
    scene.write_text(AOV_SCENE.format(nested="").replace('value="torus"', 'value="tours"'))
    assert cli.main(["render", str(scene)]) == 2
    assert "unknown surface 'tours'" in capsys.readouterr().err


def test08_warns_about_native_integrators(tmp_path, capsys):
    # Oracle: Mitsuba's own integrators cannot see lgsurfaces: the user is told.
    scene = tmp_path / "native.xml"
    scene.write_text(AOV_SCENE.format(nested="").replace(
        '<integrator type="lg_aov">\n        <string name="aovs" value="dd.y:depth,nn:sh_normal"/>',
        '<integrator type="path">'))
    assert cli.main(["render", str(scene), "-o", str(tmp_path / "x.png")]) == 0
    err = capsys.readouterr().err
    # named as the scene names it (not its C++ class, MonteCarloIntegrator),
    # with the lg integrator to use, once
    assert err.count("does not see lgsurface shapes") == 1
    assert "the integrator 'path' does not see lgsurface shapes" in err
    assert "use 'lg_path' instead" in err and "MonteCarloIntegrator" not in err


def test09_bench_is_wired(monkeypatch):
    # Oracle: `lgshape bench ARGS` calls lgshape.bench.main(ARGS).
    import sys
    import types
    seen = []
    fake = types.ModuleType("lgshape.bench")
    fake.main = lambda argv: seen.append(argv) or 0
    monkeypatch.setitem(sys.modules, "lgshape.bench", fake)
    monkeypatch.setattr(lgshape, "bench", fake, raising=False)
    assert cli.main(["bench", "--quick", "x"]) == 0
    assert seen == [["--quick", "x"]]


def camera_rays(scene, xy):
    """Mitsuba's own camera rays through film positions xy (n, 2) in [0, 1]^2
    (x right, y down), as float64 (origins, unit directions)."""
    import drjit as dr
    sensor = scene.sensors()[0]
    ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(xy[:, 0], xy[:, 1]), mi.Point2f(0.5, 0.5))
    dr.eval(ray)
    o = np.array(ray.o, dtype=np.float64).T
    d = np.array(ray.d, dtype=np.float64).T
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


def sphere_plane_depth(o, d):
    """Float64 oracle: distance to the first hit of the sphere (SPHERE_C,
    SPHERE_R) or the plane z = PLANE_Z, and whether it is the sphere."""
    oc = o - SPHERE_C
    b = np.einsum("ij,ij->i", oc, d)
    disc = b * b - (np.einsum("ij,ij->i", oc, oc) - SPHERE_R ** 2)
    t_sphere = np.where(disc > 0, -b - np.sqrt(np.maximum(disc, 0)), np.inf)
    t_sphere = np.where(t_sphere > 0, t_sphere, np.inf)
    t_plane = (PLANE_Z - o[:, 2]) / d[:, 2]
    return np.minimum(t_sphere, t_plane), t_sphere < t_plane


def pixel_footprints(res, k, grow=0.0):
    """Film positions of a k x k grid over each pixel (grown by `grow`
    pixels on each side): shape (res * res * k * k, 2), pixel-major."""
    s = np.linspace(-grow, 1 + grow, k)
    sx, sy = np.meshgrid(s, s)
    iy, ix = np.meshgrid(np.arange(res), np.arange(res), indexing="ij")
    x = (ix.reshape(-1, 1) + sx.reshape(1, -1)) / res
    y = (iy.reshape(-1, 1) + sy.reshape(1, -1)) / res
    return np.stack([x.ravel(), y.ravel()], -1)


def test14_lgsurface_drawn_where_the_oracle_says(tmp_path):
    # Oracle: a float64 ray-sphere / ray-plane intersection of Mitsuba's own
    # camera rays. A pixel whose 5x5 grid of rays (corners included) all hit
    # the sphere lies wholly on it (its projection is convex): there the
    # depth AOV is within the depths of those rays (1e-4 relative) and the
    # colour differs from the same render without the lgsurface. A pixel
    # whose grid, grown by 0.1 pixel, meets only the plane has the plane's
    # depth. 24x24 pixels, 4 spp.
    res = 24
    scene = tmp_path / "sphere.xml"
    scene.write_text(SPHERE_SCENE)
    assert cli.main(["render", str(scene), "-o", str(tmp_path / "s.exr")]) == 0
    ch = read_exr(tmp_path / "s.exr")
    depth, rgb = ch["dd.T"], ch["RGB"]
    assert depth.shape == (res, res)

    ref = mi.load_string(SPHERE_SCENE)
    t, on_sphere = sphere_plane_depth(*camera_rays(ref, pixel_footprints(res, 5)))
    t, on_sphere = t.reshape(res, res, 25), on_sphere.reshape(res, res, 25)
    _, grown_hit = sphere_plane_depth(*camera_rays(ref, pixel_footprints(res, 7, grow=0.1)))
    inside = on_sphere.all(-1)
    outside = ~grown_hit.reshape(res, res, 49).any(-1)
    assert inside.sum() > 80 and outside.sum() > 200
    lo, hi = t.min(-1) * (1 - 1e-4), t.max(-1) * (1 + 1e-4)
    pure = inside | outside
    assert np.all((depth >= lo) & (depth <= hi) | ~pure)

    bare = scene_copy(scene, tmp_path / "bare.xml", lgsurfaces=False)
    assert cli.main(["render", str(bare), "-o", str(tmp_path / "b.exr")]) == 0
    ch_bare = read_exr(tmp_path / "b.exr")
    diff = np.abs(rgb - ch_bare["RGB"]).max(-1)
    assert np.all(diff[inside] > 0.02)
    assert not np.any(ch_bare["dd.T"][inside] < lo[inside])   # the plane is behind


def test15_spp_is_honoured(tmp_path):
    # Oracle: Monte Carlo error. Against a reference of R = 2048 spp
    # (rendered here by Mitsuba directly, another seed), the mean squared
    # error of an N-spp image is sigma^2 (1/N + 1/R) per pixel, so the error
    # at --spp 1 over that at --spp 64 is (1 + 1/R) / (1/64 + 1/R) = 62.1;
    # accepted within a factor 2. A command line that ignored --spp (the
    # scene says 4) gives 1.
    res = 16
    scene = tmp_path / "sphere.xml"
    scene.write_text(SPHERE_SCENE)
    ref = np.array(mi.render(mi.load_string(SPHERE_SCENE, res=str(res)), spp=2048, seed=977),
                   dtype=np.float64)[..., :3]
    mse = {}
    for spp in (1, 64):
        out = tmp_path / f"s{spp}.exr"
        assert cli.main(["render", str(scene), "-o", str(out), "-D", f"res={res}",
                         "--spp", str(spp)]) == 0
        mse[spp] = np.mean((read_exr(out)["RGB"] - ref) ** 2)
    expected = (1 + 1 / 2048) / (1 / 64 + 1 / 2048)
    assert expected / 2 < mse[1] / mse[64] < expected * 2, mse


def test16_single_aov_keeps_its_name(tmp_path):
    # Oracle: with one one-channel AOV beside R, G, B (4 channels), the EXR
    # read back by OpenEXR has "RGB" and the AOV under its name, not RGBA.
    scene = tmp_path / "sphere.xml"
    scene.write_text(SPHERE_SCENE)
    out = tmp_path / "s.exr"
    assert cli.main(["render", str(scene), "-o", str(out), "-D", "res=8", "--spp", "1"]) == 0
    assert sorted(read_exr(out)) == ["RGB", "dd.T"]
