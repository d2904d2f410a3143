"""The libLLVM set-up that runs before Dr.Jit loads: lgshape/_llvm.py, and the
start-up hook (lgshape-llvm.pth -> _lgshape_startup.run()) that pip installs.

Oracles: the environment variable Dr.Jit reads, the error text, and the
libLLVM files actually mapped into a process (/proc/self/maps), checked
directly (with the search paths replaced where a case needs it); the exit
status and printed results of fresh Python processes started WITHOUT
DRJIT_LIBLLVM_PATH, with min/max kernels whose values are known (min of
minimum([0, 1, 2], 1) is 0, max of maximum([0, 1, 2], 1.5) is 2); and a
16x16 render by the ``mitsuba`` command whose background pixels must be the
constant emitter's radiance, 1. The cases pass whether or not an old system
LLVM (Debian 12's libllvm14/15) is installed: the control cases read which
libLLVM Dr.Jit loaded and expect the abort/error only where it is old.
"""
import json
import os
import site
import subprocess
import sys

import numpy as np
import OpenEXR
import pytest

import _lgshape_startup
from conftest import sensor_xml
from lgshape import _llvm

TIMEOUT = 120  # seconds per child process; each takes about 1-3 s
KERNEL = ("import drjit as dr; from drjit.llvm import Float; "
          "print(dr.min(dr.minimum(dr.arange(Float, 3), 1.0))[0], "
          "dr.max(dr.maximum(dr.arange(Float, 3), 1.5))[0], flush=True)")
MAPPED = ("import json, os; print(json.dumps(sorted({l.split(None, 5)[-1].strip() for l in "
          "open('/proc/self/maps') if 'libLLVM' in l})), flush=True)")


def child_env(**extra):
    """This environment without the variables under test, plus `extra`."""
    env = {k: v for k, v in os.environ.items() if k not in ("DRJIT_LIBLLVM_PATH", _llvm.HOOK_OFF)}
    env.update(extra)
    return env


def run_python(code, tmp_path, **extra):
    """`python -c code` in a fresh process, outside the source tree, without
    core dumps (some control cases abort)."""
    def no_core():
        import resource
        resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
    return subprocess.run([sys.executable, "-c", code], env=child_env(**extra), cwd=tmp_path,
                          capture_output=True, text=True, timeout=TIMEOUT, preexec_fn=no_core)


def old_only(libs):
    """True when the libLLVM files Dr.Jit mapped are all known to be too old."""
    return bool(libs) and all(0 <= _llvm._version(p) < _llvm.MIN_VERSION for p in libs)


def test01_found_library_is_recent_and_loaded():
    path = os.environ["DRJIT_LIBLLVM_PATH"]
    assert os.path.isfile(path)
    # This process (through conftest's `import lgshape`) runs Dr.Jit's LLVM
    # backend with min/max kernels without aborting:
    import drjit as dr
    from drjit.llvm import Float
    assert dr.max(dr.maximum(dr.arange(Float, 4), 2.0))[0] == 3.0
    assert _llvm.loaded() and not old_only(_llvm.loaded())


def test02_user_setting_is_respected(monkeypatch):
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", "/opt/my/libLLVM.so")
    assert _llvm.ensure() == "/opt/my/libLLVM.so"


def test03_clear_error_when_none_is_found(monkeypatch):
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    monkeypatch.setattr(_llvm, "candidates", lambda system=True: [])
    monkeypatch.setattr(_llvm, "loaded", lambda: [])
    with pytest.raises(_llvm.LLVMNotFound, match="karellen-llvm-core"):
        _llvm.ensure()


def test04_old_system_llvm_is_not_chosen():
    assert all(_llvm._version(p) >= _llvm.MIN_VERSION for p in _llvm.candidates())
    assert _llvm._version("/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1") == 15
    assert _llvm._version("/usr/lib/x86_64-linux-gnu/libLLVM-14.0.6.so.1") == 14
    assert _llvm._version("/usr/lib/llvm-19/lib/libLLVM.so.1") == 19
    assert _llvm._version("/x/lib/libLLVM.so.23.1") == 23
    assert _llvm._version("/x/lib/libLLVM.so.1") == -1
    assert _llvm.candidates(system=False) == _llvm.candidates()[:len(_llvm.candidates(system=False))]


def test05_drjit_already_loaded_an_old_llvm(monkeypatch):
    # Dr.Jit imported first (hook off) with LLVM 15 mapped: a clear error, not
    # a later abort; with a recent one mapped, that one is reported, unchanged.
    import drjit  # noqa: F401
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    monkeypatch.setattr(_llvm, "loaded", lambda: ["/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1"])
    with pytest.raises(_llvm.LLVMTooOld, match=r"libLLVM-15.so.1 \(LLVM 15\).*LGSHAPE_NO_LLVM_HOOK"):
        _llvm.ensure()
    monkeypatch.setattr(_llvm, "loaded", lambda: ["/v/lib/libLLVM.so.23.1"])
    assert _llvm.ensure() == "/v/lib/libLLVM.so.23.1"
    assert "DRJIT_LIBLLVM_PATH" not in os.environ


def test06_pth_is_installed_in_site_packages():
    # pip put the hook there (editable or not); its line runs the module.
    dirs = site.getsitepackages() + [site.getusersitepackages()]
    found = [os.path.join(d, _lgshape_startup.PTH_NAME) for d in dirs
             if os.path.isfile(os.path.join(d, _lgshape_startup.PTH_NAME))]
    assert found, f"{_lgshape_startup.PTH_NAME} not in {dirs}: reinstall lgshape with pip"
    with open(found[0]) as f:
        assert f.read() == _lgshape_startup.PTH_LINE


def test07_hook_sets_the_variable_at_start_up_cheaply(tmp_path):
    code = ("import json, os, sys, _lgshape_startup as s; print(json.dumps([os.environ.get("
            "'DRJIT_LIBLLVM_PATH'), s.path, repr(s.error), [m for m in ('numpy', 'lgshape', 'drjit', "
            "'mitsuba') if m in sys.modules]]))")
    out = run_python(code, tmp_path)
    assert out.returncode == 0 and "lgshape" not in out.stderr, out.stderr  # site printed nothing of ours
    env, path, error, heavy = json.loads(out.stdout)
    assert env == path == _llvm.candidates()[0] and error == "None"
    assert heavy == []  # the hook imports none of these


def test08_hook_keeps_the_users_setting_and_can_be_switched_off(tmp_path):
    code = "import os, _lgshape_startup as s; print(os.environ.get('DRJIT_LIBLLVM_PATH'), s.path)"
    out = run_python(code, tmp_path, DRJIT_LIBLLVM_PATH="/opt/my/libLLVM.so")
    assert (out.returncode, out.stdout.split()) == (0, ["/opt/my/libLLVM.so", "None"]), out.stderr
    out = run_python(code, tmp_path, LGSHAPE_NO_LLVM_HOOK="1")
    assert (out.returncode, out.stdout.split()) == (0, ["None", "None"]), out.stderr


def test09_hook_never_raises(tmp_path, monkeypatch):
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    monkeypatch.setattr(_lgshape_startup, "error", None)
    monkeypatch.delitem(sys.modules, "drjit", raising=False)  # as at start-up
    broken = tmp_path / "broken_llvm.py"
    broken.write_text("raise RuntimeError('boom')\n")
    assert _lgshape_startup.run(str(broken)) is None
    assert "boom" in str(_lgshape_startup.error)
    assert "DRJIT_LIBLLVM_PATH" not in os.environ


@pytest.mark.parametrize("first", [
    'import mitsuba as mi; mi.set_variant("llvm_ad_rgb"); import lgshape',
    "import drjit; import lgshape",
    "import lgshape",
], ids=["mitsuba-first", "drjit-first", "lgshape-first"])
def test10_every_import_order_runs_min_max_kernels(first, tmp_path):
    out = run_python(f"{first}; {KERNEL}", tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.split() == ["0.0", "2.0"]


SCENE = """<scene version="3.0.0">
    <integrator type="path"><integer name="max_depth" value="3"/></integrator>
    """ + sensor_xml("0, 0, 5", width=16, height=16, spp=4) + """
    <shape type="sphere"><bsdf type="diffuse"/></shape>
    <emitter type="constant"/>
</scene>
"""


def test11_mitsuba_command_renders_its_own_plugins(tmp_path):
    # Mitsuba's own command line (no lgshape import) in this environment.
    (tmp_path / "scene.xml").write_text(SCENE)
    mitsuba = os.path.join(os.path.dirname(sys.executable), "mitsuba")
    out = subprocess.run([mitsuba, "scene.xml", "-o", "out.exr"], env=child_env(), cwd=tmp_path,
                         capture_output=True, text=True, timeout=TIMEOUT)
    assert out.returncode == 0, (out.stdout + out.stderr)[-3000:]
    with OpenEXR.File(str(tmp_path / "out.exr")) as f:
        rgb = np.asarray(f.channels()["RGB"].pixels, dtype=np.float64)
    assert rgb.shape == (16, 16, 3) and np.isfinite(rgb).all()
    # Corners miss the unit sphere (seen under 2*11.5 of the 40 degrees) and
    # see the constant emitter, radiance 1; the sphere (albedo 0.5) is darker.
    assert np.all(rgb[[0, 0, -1, -1], [0, -1, 0, -1]] == 1.0)
    assert 0.3 < rgb[7:9, 7:9].mean() < 0.7


def test12_hook_off_and_drjit_first_gives_a_clear_error(tmp_path):
    # Control: the hook off and no DRJIT_LIBLLVM_PATH, drjit imported first.
    # Where Dr.Jit then loaded an old system LLVM (Debian 12's 14/15),
    # `import lgshape` must refuse with LLVMTooOld; otherwise it imports.
    code = (f"import drjit; {MAPPED}\n"
            "try:\n import lgshape\nexcept Exception as e:\n print(type(e).__name__, e)\n"
            "else:\n print('imported')")
    out = run_python(code, tmp_path, LGSHAPE_NO_LLVM_HOOK="1")
    assert out.returncode == 0, out.stderr[-3000:]
    libs, result = out.stdout.split("\n", 1)
    if old_only(json.loads(libs)):
        assert result.startswith("LLVMTooOld Dr.Jit was imported before lgshape"), result
    else:
        assert result.strip() == "imported", result


def test13_hook_off_and_no_lgshape_aborts_on_an_old_llvm(tmp_path):
    # Control for what the hook prevents: the hook off, no DRJIT_LIBLLVM_PATH,
    # no lgshape. With only an old LLVM loaded, the first min/max kernel kills
    # the process (LLVM ERROR: Cannot select ... fminimum, SIGABRT).
    out = run_python(f"import drjit; {MAPPED}; {KERNEL}", tmp_path, LGSHAPE_NO_LLVM_HOOK="1")
    libs = json.loads(out.stdout.split("\n", 1)[0])
    assert libs, out.stderr[-2000:]
    if old_only(libs):
        assert out.returncode != 0 and "LLVM ERROR" in out.stderr, (out.returncode, out.stderr[-2000:])
    elif libs:
        assert out.returncode == 0 and out.stdout.split()[-2:] == ["0.0", "2.0"], out.stderr[-3000:]
