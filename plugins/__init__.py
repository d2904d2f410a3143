"""Mitsuba plugins of lgshape: the ``lgsurface`` shape and the ``lg_path``,
``lg_direct``, ``lg_aov``, ``lg_volpath`` and ``lg_prb`` (differentiable)
integrators that render it next to native geometry. One file per plugin
id; shared integrator code is in :mod:`.common`, the emitter standing for
an lgsurface's ``area`` child in :mod:`.area`.

The last stage of the pipeline (expression -> bounds -> grid -> trace ->
plugins): only this package and the command line import Mitsuba.
"""
from __future__ import annotations

import importlib

#: plugin id -> (kind, class name); the module is ``lgshape.plugins.<id>``.
PLUGINS = {
    "lgsurface": ("shape", "LGSurface"),
    "lg_path": ("integrator", "LGPathIntegrator"),
    "lg_direct": ("integrator", "LGDirectIntegrator"),
    "lg_aov": ("integrator", "LGAOVIntegrator"),
    "lg_prb": ("integrator", "LGPRBIntegrator"),
    "lg_volpath": ("integrator", "LGVolpathIntegrator"),
}

_registered: set[str] = set()


def register_plugins() -> None:
    """Register all plugins for the current Mitsuba variant (a JIT variant:
    ``llvm_ad_rgb``, ``llvm_ad_mono``, ``llvm_ad_spectral`` or their
    ``cuda_`` siblings), and wrap ``mi.render`` so that it warns where the
    integrator cannot see the scene's lgsurfaces or ignores its media
    (:mod:`.checks`). Calling it again is a no-op."""
    import mitsuba as mi

    from . import checks

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
        getattr(mi, f"register_{kind}")(plugin_id, lambda props, cls=cls: cls(props))
    _registered.add(variant)
    checks.install_render_hook()


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
    try:
        mi.set_variant(variant)
    except Exception as err:  # e.g. a cuda_ variant without a usable GPU
        raise VariantError(f"cannot use the variant '{variant}': {err}") from None
    try:
        register_plugins()
    except RuntimeError as err:
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
