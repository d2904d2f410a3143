"""Find a libLLVM that Dr.Jit 1.5 can use, before Dr.Jit is imported.

Dr.Jit loads ``libLLVM.so`` at run time. Debian 12's default LLVM 14/15 make
the first min/max kernel abort the whole process (``Cannot select fmaximum``),
so lgshape points Dr.Jit at a recent one through ``DRJIT_LIBLLVM_PATH``:

1. a ``DRJIT_LIBLLVM_PATH`` the user set is kept as it is;
2. else the ``karellen-llvm-core`` wheel's library in this environment
   (``<prefix>/lib/libLLVM.so.*``), a dependency of lgshape;
3. else a system LLVM of version >= 16 (``/usr/lib/llvm-N``).

When none is found, :func:`ensure` raises :class:`LLVMNotFound` with what to
install, instead of letting Dr.Jit abort.
"""
from __future__ import annotations

import glob
import os
import re
import sys

MIN_VERSION = 16


class LLVMNotFound(RuntimeError):
    pass


def _version(path: str) -> int:
    """LLVM's major version from a path: .../llvm-19/lib/..., libLLVM-15.so,
    libLLVM.so.23.1 or libLLVM.so.19.1 (-1 if it cannot tell)."""
    m = re.search(r"/llvm-(\d+)/", path) or re.search(r"LLVM-(\d+)", os.path.basename(path)) \
        or re.search(r"LLVM\.so\.(\d+)\.\d+", os.path.basename(path))
    return int(m.group(1)) if m else -1


def candidates() -> list[str]:
    """Suitable libLLVM files, best first."""
    found = []
    for prefix in dict.fromkeys([sys.prefix, sys.base_prefix, os.path.dirname(os.path.dirname(sys.executable))]):
        found += sorted(glob.glob(os.path.join(prefix, "lib", "libLLVM.so.*")), key=_version, reverse=True)
    system = glob.glob("/usr/lib/llvm-*/lib/libLLVM.so*") + glob.glob("/usr/lib/*/libLLVM-*.so*") \
        + glob.glob("/usr/lib64/libLLVM*.so*")
    found += sorted(system, key=_version, reverse=True)
    return [p for p in dict.fromkeys(found) if _version(p) >= MIN_VERSION and os.path.isfile(p)]


def ensure() -> str:
    """Set ``DRJIT_LIBLLVM_PATH`` (unless the user did) and return it."""
    path = os.environ.get("DRJIT_LIBLLVM_PATH")
    if path:
        return path
    found = candidates()
    if not found:
        raise LLVMNotFound(
            f"lgshape needs libLLVM >= {MIN_VERSION} for Dr.Jit's LLVM backend "
            "(the system's LLVM 14/15 make Dr.Jit abort). Install one with "
            "'pip install karellen-llvm-core' (or 'apt-get install libllvm19'), "
            "or set DRJIT_LIBLLVM_PATH to a libLLVM.so of version >= 16.")
    os.environ["DRJIT_LIBLLVM_PATH"] = found[0]
    return found[0]
