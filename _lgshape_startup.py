"""lgshape's start-up hook: choose Dr.Jit's libLLVM before anything imports drjit.

Dr.Jit loads libLLVM when ``drjit`` is first imported, and Debian 12's LLVM
14/15 make its first min/max kernel abort the process. ``import lgshape`` sets
``DRJIT_LIBLLVM_PATH``, but that is too late when ``mitsuba``/``drjit`` was
imported first, or for the ``mitsuba`` command. So installing lgshape
(``pip install .`` or ``pip install -e .``) also puts ``lgshape-llvm.pth`` in
site-packages, whose one line (:data:`PTH_LINE`) makes :mod:`site` call
:func:`run` at every interpreter start-up of that environment.

:func:`run` does nothing when ``LGSHAPE_NO_LLVM_HOOK`` is set (to anything but
"" or "0") or ``DRJIT_LIBLLVM_PATH`` is already set; otherwise it loads
``lgshape/_llvm.py`` by path (the one copy of the search logic; the
``lgshape`` package itself, numpy and drjit are not imported) and calls its
``ensure()``, which sets ``DRJIT_LIBLLVM_PATH`` to the best libLLVM >= 16 it
finds. It never raises: with nothing found it leaves the variable unset, and
``import lgshape`` reports the problem later.

The rest of this file, :func:`__getattr__`, is build-time only: setuptools
takes the ``build_py`` command from here (``[tool.setuptools.cmdclass]`` in
pyproject.toml) to write the ``.pth`` file into the wheel, editable or not.
"""
import os
import sys

PTH_NAME = "lgshape-llvm.pth"
# A .pth line must start with "import"; an import error or an exception must
# not reach site (which would print it on every start-up).
PTH_LINE = ('import sys; exec("try:\\n import _lgshape_startup\\n _lgshape_startup.run()\\n'
            'except Exception:\\n pass")\n')
HOOK_OFF = "LGSHAPE_NO_LLVM_HOOK"

path = None   # what run() set DRJIT_LIBLLVM_PATH to (None: it set nothing)
error = None  # the exception run() swallowed, for diagnosis


def disabled() -> bool:
    return os.environ.get(HOOK_OFF, "") not in ("", "0")


def _llvm_file():
    """lgshape/_llvm.py: next to this file (site-packages, or the source tree
    for an editable install), else wherever ``lgshape`` would be imported from."""
    here = os.path.join(os.path.dirname(os.path.abspath(__file__)), "lgshape", "_llvm.py")
    if os.path.isfile(here):
        return here
    import importlib.util
    spec = importlib.util.find_spec("lgshape")  # finds, does not import
    for folder in (spec and spec.submodule_search_locations) or ():
        if os.path.isfile(os.path.join(folder, "_llvm.py")):
            return os.path.join(folder, "_llvm.py")
    return None


def run(llvm_file=None):
    """Set ``DRJIT_LIBLLVM_PATH`` unless switched off or already set; return
    what it was set to, or None. Never raises."""
    global path, error
    try:
        if disabled() or os.environ.get("DRJIT_LIBLLVM_PATH") or "drjit" in sys.modules:
            return None
        llvm_file = llvm_file or _llvm_file()
        if not llvm_file:
            return None
        from importlib.machinery import SourceFileLoader
        loader = SourceFileLoader("_lgshape_llvm", llvm_file)
        module = type(sys)("_lgshape_llvm")
        module.__file__, module.__loader__ = llvm_file, loader
        loader.exec_module(module)  # uses lgshape/__pycache__ like a normal import
        path = module.ensure()
        return path
    except Exception as e:  # LLVMNotFound included: `import lgshape` will say it
        error = e
        return None


def __getattr__(name):
    """``build_py`` for setuptools, defined on demand (start-up never needs it)."""
    if name != "build_py":
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    from setuptools.command.build_py import build_py as _build_py

    class build_py(_build_py):
        """setuptools' build_py, plus ``lgshape-llvm.pth`` at the root of the
        wheel, i.e. in site-packages once installed."""

        def _pth_target(self):
            if getattr(self, "editable_mode", False):
                # PEP 660 editable wheel (setuptools >= 64): build_lib is thrown
                # away; the wheel's root is the directory editable_wheel gave
                # the install command as install_lib.
                return self.get_finalized_command("install").install_lib
            return self.build_lib

        def run(self):
            super().run()
            target = self._pth_target()
            self.mkpath(target)
            with open(os.path.join(target, PTH_NAME), "w", encoding="ascii") as f:
                f.write(PTH_LINE)

        def get_outputs(self, include_bytecode=1):
            outputs = super().get_outputs(include_bytecode)
            if not getattr(self, "editable_mode", False):
                outputs.append(os.path.join(self.build_lib, PTH_NAME))
            return outputs

    return build_py
