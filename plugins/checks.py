"""Nothing silent: what lgshape tells the user when a scene and the
integrator that renders it do not fit.

- A Mitsuba integrator (``path``, ``volpath``, ``prb``, ``direct``, ``aov``,
  ...: anything but an lg_* integrator) cannot see lgsurface shapes: Mitsuba
  3.9.1 does not trace Python shapes, so they would be missing from the
  image. The warning names the integrator as the scene names it and the lg_*
  integrator to use instead.
- lg_path, lg_direct, lg_aov and lg_prb ignore participating media (lg_volpath
  renders them): a medium on a shape
  (native or lgsurface) or on the sensor would be left out. The warning
  names the shapes (and the sensor) that carry one, and what renders media.
- lgsurface parameters are differentiated by ``lg_prb`` only: a gradient
  enabled on one under another integrator is an error
  (:class:`NotDifferentiableError`, raised by ``mi.render``) naming it.
- A gradient pass of ``lg_prb`` that leaves out a term of the derivative it
  is asked for (the light a moving emitting lgsurface casts, silhouettes
  seen after a bounce, ...) says which, for which lgsurface
  (:meth:`LGPRBIntegrator.uncovered`, given through :func:`warn_once`).

The checks run in ``mi.render`` (:func:`install_render_hook`, called by
:func:`lgshape.register_plugins`, wraps Mitsuba 3.9.1's Python
``mitsuba.render``), in the lg integrators' ``render`` (for a direct
``integrator.render(scene)``) and in ``lgshape render``. Each warning is
given once per scene, integrator and message, as a
:class:`LGShapeWarning` (``warnings.warn``), or through the ``warn``
callback that ``lgshape render`` passes.
"""
from __future__ import annotations

import functools
import inspect
import warnings

import mitsuba as mi


class LGShapeWarning(UserWarning):
    """A scene that renders, but not as its author expects (lgsurfaces or
    media left out of the image)."""


class NotDifferentiableError(ValueError):
    """A gradient was enabled on an lgsurface parameter that the integrator
    (or lgshape) cannot differentiate."""


#: Mitsuba 3.9.1's C++ integrators: ``class_name()`` -> plugin name.
_CPP_INTEGRATORS = {
    "PathIntegrator": "path",
    "VolumetricPathIntegrator": "volpath",
    "VolpathMisIntegratorImpl": "volpathmis",
    "DirectIntegrator": "direct",
    "AOVIntegrator": "aov",
    "DepthIntegrator": "depth",
    "MomentIntegrator": "moment",
    "ParticleTracerIntegrator": "ptracer",
    "StokesIntegrator": "stokes",
}

#: Mitsuba's Python integrators live in ``mitsuba.python.ad.integrators.<plugin>``
#: (also importable as ``mitsuba.ad.integrators``).
_PY_PACKAGES = ("mitsuba.python.ad.integrators.", "mitsuba.ad.integrators.")

#: plugin name -> the lg integrator that renders the same estimate with lgsurfaces.
INSTEAD = {
    "path": "lg_path", "volpath": "lg_volpath", "volpathmis": "lg_volpath", "prb": "lg_prb",
    "prb_basic": "lg_prb", "prbvolpath": "lg_volpath", "prb_projective": "lg_prb",
    "ptracer": "lg_path",
    "direct": "lg_direct", "direct_projective": "lg_direct",
    "aov": "lg_aov", "depth": "lg_aov",
}

#: The lg integrators that ignore participating media.
NO_MEDIA = ("lg_path", "lg_direct", "lg_aov", "lg_prb")


def integrator_name(integrator) -> str:
    """The plugin name of ``integrator`` as a scene names it (``path``,
    ``prb``, ``lg_path``, ...); for an integrator outside Mitsuba and
    lgshape, its class name."""
    name = getattr(integrator, "PLUGIN", None)           # lgshape's own
    if name:
        return name
    module = type(integrator).__module__ or ""
    for package in _PY_PACKAGES:
        if module.startswith(package):
            return module[len(package):].split(".")[0]
    if module == "mitsuba":                              # a C++ plugin
        cls = integrator.class_name()
        return _CPP_INTEGRATORS.get(cls, cls)
    return type(integrator).__name__


def sees_lgsurfaces(integrator) -> bool:
    """Does this integrator trace lgsurfaces? lgshape's integrators do, and
    so does any Python integrator that sets ``SEES_LGSURFACES = True`` (one
    built on :func:`lgshape.plugins.common.ray_intersect`)."""
    return bool(getattr(integrator, "SEES_LGSURFACES", False))


def _lg_shapes(scene):
    return [s for s in scene.shapes() if getattr(s, "IS_LGSURFACE", False)]


def _names(items, most=4):
    items = list(items)
    text = ", ".join(items[:most])
    return text + (f" and {len(items) - most} more" if len(items) > most else "")


def _shape_name(shape, index, count):
    kind = "lgsurface" if getattr(shape, "IS_LGSURFACE", False) else shape.class_name()
    if shape.id():
        return f"'{shape.id()}' ({kind})"
    return f"shape {index + 1} of {count} ({kind}, no id)"


def _medium_name(medium):
    return (f"'{medium.id()}' ({medium.class_name()})" if medium.id()
            else medium.class_name())


def unseen_message(scene, integrator, lgs=None):
    """The warning for an integrator (or one nested in lg_aov) that cannot
    see the scene's lgsurfaces; None where there is nothing to say."""
    lgs = _lg_shapes(scene) if lgs is None else lgs
    if not lgs or integrator is None:
        return None
    shapes = _names(f"'{s.id()}'" if s.id() else "(no id)" for s in lgs)
    if sees_lgsurfaces(integrator):
        nested = getattr(integrator, "nested", None)
        if nested is None or sees_lgsurfaces(nested):
            return None
        name = integrator_name(nested)
        return (f"the integrator '{name}' nested in {integrator_name(integrator)} does not see "
                f"lgsurface shapes: the image channels will lack the lgsurfaces {shapes} "
                f"(its AOVs have them); nest '{INSTEAD.get(name, 'lg_path')}' instead")
    name = integrator_name(integrator)
    instead = INSTEAD.get(name)
    use = (f"use '{instead}' instead" if instead else
           "lgshape has no counterpart of it; lg_path, lg_direct and lg_aov see lgsurfaces")
    if name == "depth":
        use += " (e.g. <string name=\"aovs\" value=\"dd:depth\"/>)"
    return (f"the integrator '{name}' does not see lgsurface shapes (Mitsuba 3.9.1 cannot "
            f"trace Python shapes): the lgsurfaces {shapes} will be missing from the image; "
            f"{use}")


def media_message(scene, integrator, sensor=None, lgs=None):
    """The warning for an lg integrator that ignores the scene's media;
    None where there is nothing to say."""
    name = integrator_name(integrator) if integrator is not None else None
    if name not in NO_MEDIA:
        return None
    shapes = scene.shapes()
    carriers = []
    for i, shape in enumerate(shapes):
        for side, medium in (("interior", shape.interior_medium()),
                             ("exterior", shape.exterior_medium())):
            if medium is not None:
                carriers.append(f"the shape {_shape_name(shape, i, len(shapes))} has an "
                                f"{side} medium {_medium_name(medium)}")
    sensors = list(scene.sensors())
    if isinstance(sensor, mi.Sensor):
        sensors = [sensor]
    elif isinstance(sensor, int) and 0 <= sensor < len(sensors):
        sensors = [sensors[sensor]]
    for s in sensors:
        medium = s.get_medium()
        if medium is not None:
            which = f"'{s.id()}'" if s.id() else s.class_name()
            carriers.append(f"the sensor {which} is in the medium {_medium_name(medium)}")
    if not carriers:
        return None
    lgs = _lg_shapes(scene) if lgs is None else lgs
    if lgs:
        fix = "render it with 'lg_volpath', which renders media and sees the lgsurfaces"
    else:
        fix = "this scene has no lgsurface: render it with Mitsuba's 'volpath'"
    return (f"{name} ignores participating media, but {_names(carriers, 3)}: it renders "
            f"as if there were none; {fix}")


def differentiates_lgsurfaces(integrator) -> bool:
    """Does this integrator carry derivatives with respect to lgsurface
    parameters (``DIFFERENTIATES_LGSURFACES = True``: ``lg_prb``)?"""
    return bool(getattr(integrator, "DIFFERENTIATES_LGSURFACES", False))


def check_gradients(scene, integrator=None):
    """Raise :class:`NotDifferentiableError` where a gradient is enabled on
    an lgsurface's parameter and ``integrator`` (default: the scene's) does
    not differentiate lgsurfaces, or not that one (its
    ``refuse_uncovered_lgsurfaces(scene)``, where it has one, raises)."""
    integrator = scene.integrator() if integrator is None else integrator
    if differentiates_lgsurfaces(integrator):
        refuse = getattr(integrator, "refuse_uncovered_lgsurfaces", None)
        if refuse is not None:
            refuse(scene)
        return
    keys = [k for shape in _lg_shapes(scene) for k in shape.gradient_keys()]
    if not keys:
        return
    names = ", ".join(f"'{k}'" for k in keys)
    media = ("; 'lg_prb' leaves the scene's media out; 'lg_prbvolpath' differentiates the "
             "shapes of lgsurfaces that bound homogeneous media with a 'null' BSDF"
             if integrator_name(integrator) == "lg_volpath" else "")
    raise NotDifferentiableError(
        f"gradients are enabled on {names}, but the integrator "
        f"'{integrator_name(integrator)}' does not differentiate lgsurface parameters "
        f"(their gradients would stay 0): render with 'lg_prb'{media}, or call "
        f"dr.disable_grad() on them")


_said: set = set()


def check_render(scene, integrator=None, sensor=None, warn=None, stacklevel=2):
    """Check a render of ``scene`` with ``integrator`` (default: the
    scene's) before it starts: the warnings above, each once per scene,
    integrator and message (to ``warn(message)`` if given, else
    ``warnings.warn``), and the gradients' error."""
    if not isinstance(scene, mi.Scene):
        return
    integrator = scene.integrator() if integrator is None else integrator
    check_gradients(scene, integrator)
    lgs = _lg_shapes(scene)
    for message in (unseen_message(scene, integrator, lgs),
                    media_message(scene, integrator, sensor, lgs)):
        if message is not None:
            warn_once(scene, integrator, message, warn, stacklevel + 1)


def warn_once(scene, integrator, message, warn=None, stacklevel=2):
    """Give ``message`` once per scene, integrator and message: to
    ``warn(message)`` if given, else as an :class:`LGShapeWarning`
    (``warnings.warn``, pointing ``stacklevel`` frames up from the caller).
    Returns whether it was given now."""
    key = (scene.ptr, integrator.ptr, message)
    if key in _said:
        return False
    _said.add(key)
    if warn is not None:
        warn(message)
    else:
        warnings.warn(message, LGShapeWarning, stacklevel=stacklevel + 1)
    return True


def install_render_hook():
    """Wrap ``mitsuba.render`` (a Python function in Mitsuba 3.9.1,
    ``mitsuba.python.util.render``) so that it runs :func:`check_render`
    first. Idempotent; the original stays as ``mi.render.__wrapped__``. Code
    that took ``from mitsuba import render`` before the plugins were
    registered keeps the original (the lg integrators still check media)."""
    original = mi.render
    if getattr(original, "_lgshape_checks", False):
        return
    signature = inspect.signature(original)

    @functools.wraps(original)
    def render(*args, **kwargs):
        try:
            bound = signature.bind(*args, **kwargs).arguments
        except TypeError:
            bound = {}                       # Mitsuba reports the bad call
        check_render(bound.get("scene"), bound.get("integrator"), bound.get("sensor"),
                     stacklevel=2)
        return original(*args, **kwargs)

    render._lgshape_checks = True
    mi.render = render


__all__ = ["INSTEAD", "LGShapeWarning", "NotDifferentiableError", "check_render",
           "install_render_hook", "warn_once", "integrator_name", "media_message", "unseen_message"]
