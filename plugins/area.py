"""The area emitter of an lgsurface: Mitsuba's ``area`` emitter evaluated at
lgshape's own surface interactions.

Mitsuba's ``area`` emitter evaluates its radiance at the hit's uv and
samples its shape through the shape's C++ ``sample_position`` /
``pdf_position`` (and, for a textured radiance, its uv parameterization),
which never reach an lgsurface (a Python mesh subclass: no trampoline).
So an ``<emitter type="area">`` child of an lgsurface is replaced, when the
shape loads, by :class:`LGAreaLight`: the same radiance texture and
sampling weight, evaluated as ``area`` evaluates it (on the side the normal
points to, at the lgsurface's uv), while its sampling is the lg
integrators' (:func:`.common.sample_emitter_direction`, a traced cone
sample with an exact density). The methods Mitsuba's own sampling would
call return empty samples of density zero.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

_classes: dict = {}


class _Children(mi.TraversalCallback):
    """Collects the child objects an object's ``traverse`` lists."""

    def __init__(self):
        mi.TraversalCallback.__init__(self)
        self.objects = {}

    def put(self, name, value, flags, cpptype=None):
        if isinstance(value, mi.Object):
            self.objects[name] = value


def replace_area_light(emitter):
    """The :class:`LGAreaLight` standing for Mitsuba's area emitter
    ``emitter`` on an lgsurface (its radiance texture and sampling weight)."""
    children = _Children()
    emitter.traverse(children)
    props = mi.Properties("lg_area")
    props["radiance"] = children.objects["radiance"]
    props["sampling_weight"] = float(emitter.sampling_weight())
    return area_light_class()(props)


def area_light_class():
    """:class:`LGAreaLight` for the current variant (its base class is the
    variant's ``mi.Emitter``)."""
    variant = mi.variant()
    if variant not in _classes:
        _classes[variant] = _define()
    return _classes[variant]


def _define():
    class LGAreaLight(mi.Emitter):
        """An area emitter on an lgsurface: radiance ``radiance`` (a
        texture, evaluated at the surface's uv) leaving the side the normal
        points to. Sampled by the lg integrators, not through Mitsuba's
        emitter interface (whose sampling methods give density 0 here)."""

        def __init__(self, props):
            mi.Emitter.__init__(self, props)
            self.radiance = props.get("radiance")
            self.m_flags = mi.EmitterFlags.Surface
            if self.radiance.is_spatially_varying():
                self.m_flags = self.m_flags | mi.EmitterFlags.SpatiallyVarying

        def _radiance(self, uv, wavelengths, active):
            si = dr.zeros(mi.SurfaceInteraction3f)
            si.uv = uv
            si.wavelengths = wavelengths
            return self.radiance.eval(si, active)

        def eval(self, si, active=True):
            """The radiance at the hit ``si`` (uv from the lgsurface), 0 on
            the back side (as ``area``)."""
            front = mi.Bool(active) & (mi.Frame3f.cos_theta(si.wi) > 0)
            return dr.select(front, self.radiance.eval(si, front), 0.0)

        def eval_direction(self, it, ds, active=True):
            """The radiance reaching ``it`` from the emitter sample ``ds``
            (its point, normal and uv: :func:`.common.sample_emitter_direction`)."""
            front = mi.Bool(active) & (dr.dot(ds.d, ds.n) < 0)
            return dr.select(front, self._radiance(ds.uv, it.wavelengths, front), 0.0)

        # Mitsuba's sampling interface: not how this emitter is sampled.
        def sample_direction(self, it, sample, active=True):
            return dr.zeros(mi.DirectionSample3f), dr.zeros(mi.Spectrum)

        def pdf_direction(self, it, ds, active=True):
            return mi.Float(0)

        def sample_position(self, time, sample, active=True):
            return dr.zeros(mi.PositionSample3f), mi.Float(0)

        def pdf_position(self, ps, active=True):
            return mi.Float(0)

        def sample_ray(self, time, sample1, sample2, sample3, active=True):
            return dr.zeros(mi.Ray3f), dr.zeros(mi.Spectrum)

        def sample_wavelengths(self, si, sample, active=True):
            n = dr.size_v(mi.Spectrum)                 # Mitsuba's sample_shifted
            shifted = [sample + k / n for k in range(n)]
            shifted = mi.Spectrum(*[v - dr.floor(v) for v in shifted])
            return self.radiance.sample_spectrum(si, shifted, active)

        def traverse(self, callback):
            callback.put("radiance", self.radiance, mi.ParamFlags.Differentiable)

        def to_string(self):
            return f"LGAreaLight[\n  radiance = {self.radiance}\n]"

    return LGAreaLight
