"""Find a libLLVM that Dr.Jit 1.5 can use, before Dr.Jit is imported.

Dr.Jit loads ``libLLVM.so`` when ``drjit`` is first imported. Debian 12's
default LLVM 14/15 make the first min/max kernel abort the whole process
(``Cannot select fmaximum``), so lgshape points Dr.Jit at a recent one through
``DRJIT_LIBLLVM_PATH``:

1. a ``DRJIT_LIBLLVM_PATH`` the user set is kept as it is;
2. else the ``karellen-llvm-core`` wheel's library in this environment
   (``<prefix>/lib/libLLVM.so.*``), a dependency of lgshape;
3. else a system LLVM of version >= 16 (``/usr/lib/llvm-N``).

This runs twice: at interpreter start-up, through the ``lgshape-llvm.pth``
file that installing lgshape puts in site-packages (``_lgshape_startup.py``
loads this file by path, without importing the ``lgshape`` package, and calls
:func:`ensure` quietly; ``LGSHAPE_NO_LLVM_HOOK=1`` switches that off), and at
``import lgshape``. When none is found, :func:`ensure` raises
:class:`LLVMNotFound` with what to install, instead of letting Dr.Jit abort;
when Dr.Jit was imported earlier and already loaded an old libLLVM, it raises
:class:`LLVMTooOld`.

This module runs in every Python start-up of the environment, so it imports
only ``os`` and ``sys`` (no ``re``/``glob``: they would add milliseconds).
"""
import os
import sys

MIN_VERSION = 16
HOOK_OFF = "LGSHAPE_NO_LLVM_HOOK"
_DIGITS = "0123456789"


class LLVMNotFound(RuntimeError):
    pass


class LLVMTooOld(LLVMNotFound):
    """Dr.Jit was imported before lgshape and has already loaded a libLLVM
    older than :data:`MIN_VERSION`; its first min/max kernel would abort."""


def _number(text: str, marker: str, then: str = "") -> int:
    """The decimal number right after ``marker`` in ``text`` whose digits are
    followed by ``then`` (and, when ``then`` is ".", by a digit after it);
    -1 if there is none."""
    start = text.find(marker)
    while start >= 0:
        i = end = start + len(marker)
        while end < len(text) and text[end] in _DIGITS:
            end += 1
        if end > i and text.startswith(then, end) and (
                then != "." or text[end + 1:end + 2].isdigit()):
            return int(text[i:end])
        start = text.find(marker, start + 1)
    return -1


def _version(path: str) -> int:
    """LLVM's major version from a path: .../llvm-19/lib/..., libLLVM-15.so,
    libLLVM.so.23.1 or libLLVM.so.19.1 (-1 if it cannot tell)."""
    name = os.path.basename(path)
    for v in (_number(path, "/llvm-", "/"), _number(name, "LLVM-"), _number(name, "LLVM.so.", ".")):
        if v >= 0:
            return v
    return -1


def _files(folder: str, prefix: str, contains: str = "") -> list[str]:
    """Paths in ``folder`` whose names start with ``prefix`` and contain
    ``contains`` after it (like glob's ``prefix*contains*``), sorted; [] when
    ``folder`` is missing or not a folder."""
    try:
        names = os.listdir(folder)
    except OSError:
        return []
    return [os.path.join(folder, n) for n in sorted(names)
            if n.startswith(prefix) and contains in n[len(prefix):]]


def candidates(system: bool = True) -> list[str]:
    """Suitable libLLVM files, best first (only the Python environment's own
    unless ``system``)."""
    found = []
    for prefix in dict.fromkeys([sys.prefix, sys.base_prefix, os.path.dirname(os.path.dirname(sys.executable))]):
        found += sorted(_files(os.path.join(prefix, "lib"), "libLLVM.so."), key=_version, reverse=True)
    if system:
        libs = [p for d in _files("/usr/lib", "llvm-") for p in _files(os.path.join(d, "lib"), "libLLVM.so")]
        libs += [p for d in _files("/usr/lib", "") for p in _files(d, "libLLVM-", ".so")]
        libs += _files("/usr/lib64", "libLLVM", ".so")
        found += sorted(libs, key=_version, reverse=True)
    return [p for p in dict.fromkeys(found) if _version(p) >= MIN_VERSION and os.path.isfile(p)]


def loaded() -> list[str]:
    """libLLVM files mapped into this process (from /proc/self/maps; [] where
    that cannot be read)."""
    try:
        with open("/proc/self/maps") as f:
            paths = [line.split(None, 5)[-1].strip() for line in f if "libLLVM" in line]
    except OSError:
        return []
    return [p for p in dict.fromkeys(paths) if "libLLVM" in os.path.basename(p)]


def _check_loaded() -> str | None:
    """If Dr.Jit is already imported: the libLLVM it loaded when it is recent
    (or of unknown version); :class:`LLVMTooOld` when it is old; None when no
    libLLVM is mapped (Dr.Jit not imported, or it found none)."""
    if "drjit" not in sys.modules:
        return None
    libs = loaded()
    good = [p for p in libs if _version(p) >= MIN_VERSION or _version(p) < 0]
    if good:
        return good[0]
    if libs:
        hint = candidates()
        fix = (f"set DRJIT_LIBLLVM_PATH={hint[0]} before Python starts" if hint
               else "install 'karellen-llvm-core' (or 'apt-get install libllvm19')")
        raise LLVMTooOld(
            f"Dr.Jit was imported before lgshape and loaded {libs[0]} (LLVM {_version(libs[0])}); "
            f"Dr.Jit needs LLVM >= {MIN_VERSION} and its first min/max kernel would abort the process. "
            f"lgshape's start-up hook (lgshape-llvm.pth) normally prevents this: unset {HOOK_OFF}, "
            f"import lgshape before drjit/mitsuba, or {fix}.")
    return None


def ensure() -> str:
    """Set ``DRJIT_LIBLLVM_PATH`` (unless the user did) and return it. When
    Dr.Jit is already imported it is too late to choose: raise
    :class:`LLVMTooOld` if the libLLVM it loaded is too old, else (variable
    unset) return that library."""
    in_use = _check_loaded()
    path = os.environ.get("DRJIT_LIBLLVM_PATH") or in_use
    if path:
        return path
    found = candidates(system=False) or candidates()  # the first is enough, and cheaper
    if not found:
        raise LLVMNotFound(
            f"lgshape needs libLLVM >= {MIN_VERSION} for Dr.Jit's LLVM backend "
            "(the system's LLVM 14/15 make Dr.Jit abort). Install one with "
            "'pip install karellen-llvm-core' (or 'apt-get install libllvm19'), "
            "or set DRJIT_LIBLLVM_PATH to a libLLVM.so of version >= 16.")
    os.environ["DRJIT_LIBLLVM_PATH"] = found[0]
    return found[0]
