"""The ``lg_aov`` integrator: Mitsuba's ``aov`` for scenes with lgsurfaces."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from lgshape.trace import collection_paused

from . import common, frozen
from .common import ray_intersect

#: AOV type -> channel suffixes (the names Mitsuba 3.9.1's ``aov`` gives).
AOV_TYPES = {
    "depth": (".T",),
    "position": (".X", ".Y", ".Z"),
    "uv": (".U", ".V"),
    "geo_normal": (".X", ".Y", ".Z"),
    "sh_normal": (".X", ".Y", ".Z"),
}


class LGAOVIntegrator(mi.SamplingIntegrator):
    r"""
    .. _integrator-lg_aov:

    Arbitrary output variables for implicit surfaces (:monosp:`lg_aov`)
    --------------------------------------------------------------------

    .. pluginparameters::

     * - aovs
       - |string|
       - Comma-separated ``<name>:<type>`` pairs, as for Mitsuba's ``aov``,
         e.g. ``dd.y:depth,nn:sh_normal``. Types: ``depth`` (distance along
         the camera ray, 0 where nothing is hit), ``position`` (world),
         ``uv``, ``geo_normal``, ``sh_normal`` (the shape's shading normal;
         normal-mapping BSDFs are not applied).
     * - (Nested plugin)
       - |integrator|
       - Optional: one integrator (e.g. ``lg_path``) whose image fills the
         R, G, B channels; without it the rendered image holds the AOV
         channels alone (as Mitsuba's ``aov`` returns it).

    Channels are named as by Mitsuba's ``aov``: ``<name>.T`` for depth,
    ``<name>.X/.Y/.Z`` for positions and normals, ``<name>.U/.V`` for uv.
    Values describe the nearest surface, native or ``lgsurface``, and are 0
    where the ray escapes. Participating media are ignored (a warning names
    the shapes that carry one), and a nested integrator that cannot see
    lgsurfaces (Mitsuba's ``path``) is warned about.

    .. tabs::

        .. code-tab:: xml

            <integrator type="lg_aov">
                <string name="aovs" value="dd.y:depth,nn:sh_normal"/>
                <integrator type="lg_path" name="image"/>
            </integrator>

        .. code-tab:: python

            'type': 'lg_aov',
            'aovs': 'dd.y:depth,nn:sh_normal',
            'image': {'type': 'lg_path'}
    """

    PLUGIN = "lg_aov"                   # the plugin name (:func:`.checks.integrator_name`)
    SEES_LGSURFACES = True              # traces lgsurfaces (:func:`.checks.sees_lgsurfaces`)

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        self.aovs = []                                    # (name, type)
        for token in props.get("aovs", "").split(","):
            token = token.strip()
            if not token:
                continue
            name, sep, kind = (s.strip() for s in token.partition(":"))
            if not sep or not name or not kind:
                raise ValueError(f"lg_aov: invalid AOV '{token}': expected <name>:<type>")
            if kind not in AOV_TYPES:
                raise ValueError(f"lg_aov: unknown AOV type '{kind}' in '{token}'; "
                                 f"supported: {', '.join(AOV_TYPES)}")
            self.aovs.append((name, kind))
        nested = [props.get(k) for k in props.keys()
                  if props.type(k) == mi.Properties.Type.Object]
        if any(not isinstance(n, mi.SamplingIntegrator) for n in nested) or len(nested) > 1:
            raise ValueError("lg_aov: takes at most one nested integrator (e.g. lg_path)")
        self.nested = nested[0] if nested else None
        if not self.aovs and self.nested is None:
            raise ValueError("lg_aov: no AOVs given: set 'aovs', e.g. 'dd.y:depth,nn:sh_normal'")

    def sample(self, scene: mi.Scene, sampler: mi.Sampler, ray: mi.RayDifferential3f,
               medium: mi.Medium = None, active: mi.Bool = True):
        active = mi.Bool(active)
        si = ray_intersect(scene, ray, active)
        hit = active & si.is_valid()
        si = dr.select(hit, si, dr.zeros(mi.SurfaceInteraction3f))

        values = []
        for _, kind in self.aovs:
            if kind == "depth":
                values.append(dr.select(hit, si.t, 0.0))
            elif kind == "position":
                values += list(si.p)
            elif kind == "uv":
                values += list(si.uv)
            elif kind == "geo_normal":
                values += list(si.n)
            elif kind == "sh_normal":
                values += list(si.sh_frame.n)

        if self.nested is None:
            return mi.Spectrum(0), hit, values
        L, valid, nested_aovs = self.nested.sample(scene, sampler, ray, medium, active)
        return L, valid, values + list(nested_aovs)

    @collection_paused()
    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        """Mitsuba's render (:func:`.frozen.sampling_render`); without a nested
        integrator the image holds the AOV channels alone, as Mitsuba's
        ``aov`` returns it (the film keeps its R, G, B channels, at 0)."""
        image = frozen.sampling_render(self, scene, sensor, seed, spp, develop, evaluate)
        n = len(self.aov_names())
        if self.nested is None and develop and image.shape[2] > n:
            # (Mitsuba's render enters this method again with the sensor
            # object: the inner call's image is already sliced, and slicing
            # it again would cost a gather kernel)
            image = image[..., image.shape[2] - n:]
        return image

    def aov_names(self):
        names = [name + suffix for name, kind in self.aovs for suffix in AOV_TYPES[kind]]
        if self.nested is not None:
            names += list(self.nested.aov_names())
        return names

    def to_string(self):
        aovs = ", ".join(f"{n}:{k}" for n, k in self.aovs)
        return f"LGAOVIntegrator[\n  aovs = [{aovs}],\n  nested = {self.nested}\n]"
