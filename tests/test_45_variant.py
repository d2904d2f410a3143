"""``--variant cuda_*`` where Dr.Jit has no CUDA backend: the command says
that no CUDA device was found, before it loads the scene.

Oracle: Dr.Jit's own report of its CUDA backend
(``dr.has_backend(dr.JitBackend.CUDA)``, which is false exactly where
Mitsuba's ``set_variant('cuda_...')`` later fails with "the CUDA backend
hasn't been initialized"); on a machine with a GPU the same variants must
be usable.
"""
import lgshape  # noqa: F401  (before mitsuba: sets up libLLVM)
import drjit as dr
import mitsuba as mi
import pytest

from lgshape import cli
from lgshape.plugins import VariantError, use_variant

CUDA_VARIANTS = [v for v in mi.variants() if v.startswith("cuda_") and "polarized" not in v]
HAS_CUDA = bool(dr.has_backend(dr.JitBackend.CUDA))

SCENE = """<scene version="3.0.0">
    <integrator type="lg_path"/>
    <sensor type="perspective"><film type="hdrfilm"><integer name="width" value="4"/>
        <integer name="height" value="4"/></film>
        <sampler type="independent"><integer name="sample_count" value="1"/></sampler></sensor>
    <shape type="lgsurface"><string name="surface" value="torus"/></shape>
</scene>"""


@pytest.fixture(autouse=True)
def restore_variant():
    before = mi.variant()
    yield
    if before is not None:
        mi.set_variant(before)


@pytest.mark.skipif(HAS_CUDA, reason="this machine has a CUDA device")
@pytest.mark.parametrize("variant", CUDA_VARIANTS)
def test01_no_cuda_device_is_said(tmp_path, capsys, variant):
    xml = tmp_path / "s.xml"
    xml.write_text(SCENE)
    assert cli.main(["render", str(xml), "-o", str(tmp_path / "x.png"),
                     "--variant", variant]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"lgshape: error: cannot use the variant '{variant}': "
                          "no CUDA device was found")
    assert f"--variant {variant.replace('cuda_', 'llvm_')}" in err
    assert "hasn't been initialized" not in err
    assert not (tmp_path / "x.png").exists()
    # the same from Python (what the Dask workers call)
    with pytest.raises(VariantError, match="no CUDA device was found"):
        use_variant(variant)


@pytest.mark.skipif(HAS_CUDA, reason="this machine has a CUDA device")
def test02_frames_say_it_too(tmp_path, capsys):
    xml = tmp_path / "s.xml"
    xml.write_text(SCENE)
    assert cli.main(["render", str(xml), "-o", str(tmp_path / "f.png"), "--frames", "2",
                     "--variant", "cuda_ad_rgb"]) == 2
    assert "no CUDA device was found" in capsys.readouterr().err


@pytest.mark.skipif(not HAS_CUDA, reason="no CUDA device here")
@pytest.mark.parametrize("variant", CUDA_VARIANTS)
def test03_cuda_variants_usable_with_a_device(variant):
    assert use_variant(variant).variant() == variant
