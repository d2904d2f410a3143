"""The libLLVM set-up that runs before Dr.Jit loads.

Oracle: the environment variable Dr.Jit reads, and the error text, checked
directly (with the search paths replaced where a case needs it)."""
import os
import subprocess
import sys

import pytest

from lgshape import _llvm


def test01_found_library_is_recent_and_loaded():
    path = os.environ["DRJIT_LIBLLVM_PATH"]
    assert os.path.isfile(path)
    # This process (through conftest's `import lgshape`) runs Dr.Jit's LLVM
    # backend with min/max kernels without aborting:
    import drjit as dr
    from drjit.llvm import Float
    assert dr.max(dr.maximum(dr.arange(Float, 4), 2.0))[0] == 3.0


def test02_user_setting_is_respected(monkeypatch):
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", "/opt/my/libLLVM.so")
    assert _llvm.ensure() == "/opt/my/libLLVM.so"


def test03_clear_error_when_none_is_found(monkeypatch):
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    monkeypatch.setattr(_llvm, "candidates", lambda: [])
    with pytest.raises(_llvm.LLVMNotFound, match="karellen-llvm-core"):
        _llvm.ensure()


def test04_old_system_llvm_is_not_chosen():
    assert all(_llvm._version(p) >= _llvm.MIN_VERSION for p in _llvm.candidates())
    assert _llvm._version("/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1") == 15
    assert _llvm._version("/usr/lib/llvm-19/lib/libLLVM.so.1") == 19
    assert _llvm._version("/x/lib/libLLVM.so.23.1") == 23


def test05_fresh_process_imports_without_abort():
    env = {k: v for k, v in os.environ.items() if k != "DRJIT_LIBLLVM_PATH"}
    code = ("import lgshape, drjit as dr; from drjit.llvm import Float; "
            "print(dr.min(dr.minimum(dr.arange(Float, 3), 1.0))[0])")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "0.0"
