"""The scenes in ``scenes/`` and the ``lgshape`` command line.

Oracles: every scene renders through the command line at a tiny size (set
with ``-D``, as the README promises) to finite, non-black images of that
size; the EXR's channel names are read back with the OpenEXR package (not
with Mitsuba, which wrote them); bad input gives the documented messages
and exit status 2.
"""
import os
import pathlib

import lgshape  # noqa: F401  (before mitsuba: sets up libLLVM)
import mitsuba as mi
import numpy as np
import OpenEXR
import pytest

from lgshape import cli

SCENES = sorted((pathlib.Path(__file__).parent.parent / "scenes").glob("*.xml"))

AOV_SCENE = """<scene version="3.0.0">
    <default name="resx" value="12"/>
    <default name="resy" value="10"/>
    <integrator type="lg_aov">
        <string name="aovs" value="dd.y:depth,nn:sh_normal"/>
        {nested}
    </integrator>
    <sensor type="perspective">
        <transform name="to_world">
            <lookat origin="0, 0, 7" target="0, 0, 0" up="0, 1, 0"/>
        </transform>
        <sampler type="independent"><integer name="sample_count" value="2"/></sampler>
        <film type="hdrfilm">
            <integer name="width" value="$resx"/><integer name="height" value="$resy"/>
            <rfilter type="box"/>
        </film>
    </sensor>
    <shape type="lgsurface"><string name="surface" value="torus"/></shape>
    <emitter type="constant"/>
</scene>
"""


@pytest.fixture(autouse=True)
def variant():
    mi.set_variant("llvm_ad_rgb")
    lgshape.register_plugins()


def read_exr(path):
    with OpenEXR.File(str(path)) as f:
        return {name: np.asarray(ch.pixels) for name, ch in f.channels().items()}


def test01_scenes_exist():
    # Oracle: the list (a Cornell showcase, one scene per class of
    # library surface, one mixed scene).
    names = {p.stem for p in SCENES}
    assert {"cornell", "algebraic", "soft", "periodic", "spikes", "mixed"} <= names


@pytest.mark.parametrize("scene", SCENES, ids=lambda p: p.stem)
def test02_scene_renders_tiny(scene, tmp_path):
    # Oracle: a 16x12 image with finite values that is not black, and a PNG
    # beside the EXR; every scene declares the spp/resx/resy defaults.
    text = scene.read_text()
    for name in ("spp", "resx", "resy"):
        assert f'<default name="{name}"' in text
    out = tmp_path / f"{scene.stem}.exr"
    assert cli.main(["render", str(scene), "-o", str(out),
                     "-D", "resx=16", "-D", "resy=12", "-D", "spp=2"]) == 0
    rgb = read_exr(out)["RGB"]
    assert rgb.shape == (12, 16, 3)
    assert np.all(np.isfinite(rgb)) and rgb.mean() > 0.01
    assert (tmp_path / f"{scene.stem}.png").stat().st_size > 0


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


@pytest.mark.parametrize("args, message", [
    (["-D", "resx"], "-D expects name=value, got 'resx'"),
    (["--variant", "scalar_rgb"], "'scalar_rgb' is a scalar variant"),
    (["--variant", "llvm_rgb_nope"], "unknown variant 'llvm_rgb_nope'"),
    (["-o", "x.jpg"], "the output must end in .exr or .png"),
])
def test06_errors(tmp_path, capsys, args, message):
    # Oracle: exit status 2 and the message on stderr.
    scene = tmp_path / "aov.xml"
    scene.write_text(AOV_SCENE.format(nested=""))
    assert cli.main(["render", str(scene), *args]) == 2
    assert message in capsys.readouterr().err


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
    assert "does not see lgsurface shapes" in capsys.readouterr().err


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
