"""Mitsuba plugins of lgshape: the ``lgsurface`` shape and the ``lg_path``,
``lg_direct``, ``lg_aov``, ``lg_volpath`` and ``lg_prb`` (differentiable)
integrators that render it next to native geometry. One file per plugin
id; shared integrator code is in :mod:`.common`, the emitter standing for
an lgsurface's ``area`` child in :mod:`.area`.

The last stage of the pipeline (expression -> bounds -> grid -> trace ->
plugins): only this package and the command line import Mitsuba.

:func:`register_plugins` registers them for the current variant and, from
then on, for each JIT variant that ``mi.set_variant`` switches to (a Mitsuba
variant callback). It wraps ``mi.load_dict``, ``mi.load_file`` and
``mi.load_string`` so that an error of an lgshape plugin's constructor,
which Mitsuba reports as a ``RuntimeError`` with the Python traceback in its
message, arrives as lgshape raised it: its own type (e.g.
:class:`lgshape.ParseError`, ``ValueError``), made a subclass of
``RuntimeError`` too, so that ``except RuntimeError`` still catches it, and
its own message, followed by where Mitsuba was loading
(``at dictionary node "ball"``, ``at scene.xml (line 3, col 6)``).
"""
from __future__ import annotations

import functools
import importlib
import re
import threading

#: plugin id -> (kind, class name); the module is ``lgshape.plugins.<id>``.
PLUGINS = {
    "lgsurface": ("shape", "LGSurface"),
    "lg_path": ("integrator", "LGPathIntegrator"),
    "lg_direct": ("integrator", "LGDirectIntegrator"),
    "lg_aov": ("integrator", "LGAOVIntegrator"),
    "lg_prb": ("integrator", "LGPRBIntegrator"),
    "lg_volpath": ("integrator", "LGVolpathIntegrator"),
    "lg_prbvolpath": ("integrator", "LGPRBVolpathIntegrator"),
}

_registered: set[str] = set()


def register_plugins() -> None:
    """Register all plugins for the current Mitsuba variant (a JIT variant:
    ``llvm_ad_rgb``, ``llvm_ad_mono``, ``llvm_ad_spectral`` or their
    ``cuda_`` siblings) and for every JIT variant set later (through
    ``mi.detail.add_variant_callback``: no second call is needed after
    ``mi.set_variant``); wrap ``mi.render`` so that it warns where the
    integrator cannot see the scene's lgsurfaces or ignores its media
    (:mod:`.checks`), and ``mi.load_dict`` / ``load_file`` / ``load_string``
    so that the plugins' errors arrive as themselves (see the module).
    Calling it again is a no-op."""
    import mitsuba as mi

    from . import checks

    _install_load_hooks(mi)
    _follow_variants(mi)
    variant = mi.variant()
    if variant is None:
        raise RuntimeError("lgshape.register_plugins(): no Mitsuba variant is set; call "
                           "mi.set_variant('llvm_ad_rgb') (or another JIT variant) first")
    if variant.startswith("scalar"):
        raise RuntimeError(f"lgshape.register_plugins(): the variant '{variant}' is a scalar "
                           "variant; lgshape traces rays with Dr.Jit and needs a JIT variant "
                           "such as 'llvm_ad_rgb' or 'cuda_ad_rgb'")
    if "polarized" in variant:
        raise RuntimeError(f"lgshape.register_plugins(): polarized variants ('{variant}') are "
                           "not supported; use e.g. 'llvm_ad_rgb' or 'llvm_ad_spectral'")
    if variant in _registered:
        return
    for plugin_id, (kind, class_name) in PLUGINS.items():
        module = importlib.import_module(f".{plugin_id}", __name__)
        # Classes derive from the variant's base classes: rebuild them for a
        # new variant (as Mitsuba does for its own Python integrators).
        if getattr(module, "_variant", variant) != variant:
            module = importlib.reload(module)
        module._variant = variant
        cls = getattr(module, class_name)
        getattr(mi, f"register_{kind}")(plugin_id, functools.partial(_construct, cls))
    _registered.add(variant)
    checks.install_render_hook()


def _follow_variants(mi):
    """Register the plugins for each JIT variant ``mi.set_variant`` sets
    from now on (Mitsuba calls its variant callbacks after a change, as it
    does for its own Python integrators). Scalar and polarized variants are
    skipped: there :func:`register_plugins` itself says why it cannot."""
    detail = getattr(mi, "detail", None)
    if detail is None or not hasattr(detail, "add_variant_callback"):
        return                                   # (a Mitsuba without callbacks)
    detail.add_variant_callback(_variant_changed)    # (Mitsuba keeps one copy)


def _variant_changed(old, new):
    if new is None or new.startswith("scalar") or "polarized" in new or new in _registered:
        return
    register_plugins()


# ---- Errors of the plugins' constructors through mi.load_* -----------------

#: Exceptions raised by the plugins' constructors, newest last (a few):
#: Mitsuba turns them into a RuntimeError holding their text, and the
#: wrapped loaders (:func:`_install_load_hooks`) raise them instead.
_raised: list = []
_raised_lock = threading.Lock()


def _construct(cls, props):
    try:
        return cls(props)
    except Exception as err:
        with _raised_lock:
            _raised.append(err)
            del _raised[:-8]
        raise


def _take_raised(message):
    """The newest kept exception whose text is in Mitsuba's ``message``
    (removed from the list), or None."""
    with _raised_lock:
        for i in range(len(_raised) - 1, -1, -1):
            text = str(_raised[i])
            if text and text in message:
                return _raised.pop(i)
    return None


#: (exception class) -> its subclass that is also a RuntimeError
_load_types: dict = {}


def _as_load_error(err, message):
    """``err`` as a loader raises it: of a subclass of its class and of
    RuntimeError (what Mitsuba's loaders raise), named as its class, with its
    text and attributes, then where Mitsuba was (from ``message``)."""
    cls = type(err)
    if not isinstance(err, RuntimeError):
        if cls not in _load_types:
            try:
                _load_types[cls] = type(cls.__name__, (cls, RuntimeError),
                                        {"__module__": cls.__module__, "__doc__": cls.__doc__,
                                         "__qualname__": cls.__qualname__})
            except TypeError:                    # (a layout RuntimeError cannot share)
                _load_types[cls] = cls
        cls = _load_types[cls]
    new = err if cls is type(err) else cls.__new__(cls, *err.args)
    new.__dict__.update(err.__dict__)
    text = str(err)
    where = re.search(r"At (.*?): failed to instantiate", message)
    if where:
        text += f"\n  at {where.group(1)}"
    new.args = (text,) + tuple(err.args[1:]) if len(err.args) <= 1 else err.args
    new.__cause__ = err.__cause__
    return new.with_traceback(err.__traceback__)


def _install_load_hooks(mi):
    """Wrap ``mi.load_dict``, ``mi.load_file`` and ``mi.load_string``
    (Mitsuba's loaders, one for all variants): a RuntimeError caused by an
    lgshape plugin's constructor is raised as that plugin's exception
    (:func:`_as_load_error`). Idempotent; the originals stay as
    ``__wrapped__``."""
    for name in ("load_dict", "load_file", "load_string"):
        original = getattr(mi, name)
        if getattr(original, "_lgshape_errors", False):
            continue

        def load(*args, __original=original, **kwargs):
            try:
                return __original(*args, **kwargs)
            except RuntimeError as err:
                raised = _take_raised(str(err))
                if raised is None:
                    raise
                raise _as_load_error(raised, str(err)) from None
        functools.update_wrapper(load, original)
        load._lgshape_errors = True
        setattr(mi, name, load)


class VariantError(ValueError):
    """A Mitsuba variant that cannot be used here (unknown, scalar, polarized,
    or cuda_ without a CUDA device)."""


def use_variant(variant):
    """Set the Mitsuba variant and register lgshape's plugins for it; returns
    the mitsuba module. The one set-up of a rendering process: the command
    line and the Dask workers of :mod:`lgshape.frames` go through it."""
    import mitsuba as mi
    if variant not in mi.variants():
        raise VariantError(f"unknown variant '{variant}'; this Mitsuba has "
                           f"{', '.join(mi.variants())}")
    if variant.startswith("cuda_"):
        _check_cuda(variant)
    previous = mi.variant()
    try:
        mi.set_variant(variant)
    except Exception as err:  # e.g. a cuda_ variant without a usable GPU
        raise VariantError(f"cannot use the variant '{variant}': {err}") from None
    try:
        register_plugins()
    except RuntimeError as err:
        if previous is not None:            # (a refused variant is not left set)
            mi.set_variant(previous)
        raise VariantError(str(err)) from None
    return mi


def _check_cuda(variant):
    """A cuda_ variant needs Dr.Jit's CUDA backend, which Dr.Jit initialises
    when it is imported if it finds a GPU: without one, say so (Mitsuba's own
    message, "the CUDA backend hasn't been initialized", comes later and
    names no cause)."""
    import drjit as dr
    if dr.has_backend(dr.JitBackend.CUDA):
        return
    import ctypes.util
    why = ("no CUDA driver (libcuda.so) is installed" if ctypes.util.find_library("cuda") is None
           else "the CUDA driver found no usable GPU")
    raise VariantError(f"cannot use the variant '{variant}': no CUDA device was found "
                       f"({why}; Dr.Jit's CUDA backend did not start). Render on the CPU "
                       f"with --variant {variant.replace('cuda_', 'llvm_', 1)}")

def __getattr__(name):
    if name in ("LGShapeWarning", "NotDifferentiableError"):
        from . import checks
        return getattr(checks, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = ["LGShapeWarning", "NotDifferentiableError", "PLUGINS", "register_plugins"]
