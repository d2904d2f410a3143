"""The ``lg_direct`` integrator: Mitsuba's ``direct`` for scenes with lgsurfaces."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from . import common, frozen
from .common import (compute_interaction, mis_weight, pdf_emitter_direction, ray_intersect,
                     ray_intersect_preliminary, ray_test, sample_emitter_direction,
                     skip_area_emitters)


class LGDirectIntegrator(mi.SamplingIntegrator):
    r"""
    .. _integrator-lg_direct:

    Direct illumination for implicit surfaces (:monosp:`lg_direct`)
    ---------------------------------------------------------------

    .. pluginparameters::

     * - shading_samples
       - |int|
       - Sets both ``emitter_samples`` and ``bsdf_samples``. (Default: 1)
     * - emitter_samples
       - |int|
       - Emitter samples per camera sample. (Default: ``shading_samples``)
     * - bsdf_samples
       - |int|
       - BSDF samples per camera sample. (Default: ``shading_samples``)
     * - hide_emitters
       - |bool|
       - Hide directly visible emitters. (Default: |false|)

    Direct illumination with the estimator of Mitsuba's ``direct``: emitter
    and BSDF samples combined by multiple importance sampling (power
    heuristic), no indirect light. It sees native shapes and every
    ``lgsurface`` in the scene; its shadow rays test both. Participating
    media are ignored (a warning names the shapes that carry one).

    .. tabs::

        .. code-tab:: xml

            <integrator type="lg_direct">
                <integer name="emitter_samples" value="4"/>
            </integrator>

        .. code-tab:: python

            'type': 'lg_direct',
            'emitter_samples': 4
    """

    PLUGIN = "lg_direct"                # the plugin name (:func:`.checks.integrator_name`)
    SEES_LGSURFACES = True              # traces lgsurfaces (:func:`.checks.sees_lgsurfaces`)

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        if "shading_samples" in props and ("emitter_samples" in props or "bsdf_samples" in props):
            raise ValueError("lg_direct: give either 'shading_samples' or "
                             "'emitter_samples'/'bsdf_samples', not both")
        shading = int(props.get("shading_samples", 1))
        self.emitter_samples = int(props.get("emitter_samples", shading))
        self.bsdf_samples = int(props.get("bsdf_samples", shading))
        if self.emitter_samples < 0 or self.bsdf_samples < 0 or \
                self.emitter_samples + self.bsdf_samples == 0:
            raise ValueError("lg_direct: needs at least one emitter or BSDF sample")
        total = self.emitter_samples + self.bsdf_samples
        self.frac_em, self.frac_bsdf = self.emitter_samples / total, self.bsdf_samples / total

    def sample(self, scene: mi.Scene, sampler: mi.Sampler, ray: mi.RayDifferential3f,
               medium: mi.Medium = None, active: mi.Bool = True):
        active = mi.Bool(active)
        hit = ray_intersect_preliminary(scene, ray, active)
        if self.hide_emitters:
            ray, hit = skip_area_emitters(scene, ray, hit, active)
        si = compute_interaction(scene, ray, hit, active=active)
        L = mi.Spectrum(0)

        # ----------------------- Visible emitters -----------------------
        if not self.hide_emitters:
            L += si.emitter(scene, active).eval(si, active)

        valid_ray = active & si.is_valid()
        active = mi.Bool(valid_ray)
        bsdf_ctx = mi.BSDFContext()
        bsdf = si.bsdf(ray)

        # ----------------------- Emitter sampling -----------------------
        active_em = active & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
        for _ in range(self.emitter_samples):
            ds, em_weight, tested = sample_emitter_direction(scene, si,
                                                             sampler.next_2d(active_em),
                                                             active_em)
            active_e = active_em & (ds.pdf != 0)
            active_e &= ~ray_test(scene, si.spawn_ray_to(ds.p), active_e & ~tested)
            wo = si.to_local(ds.d)
            bsdf_val, bsdf_pdf = bsdf.eval_pdf(bsdf_ctx, si, wo, active_e)
            mis = dr.select(ds.delta, 1.0, mis_weight(ds.pdf * self.frac_em,
                                                      bsdf_pdf * self.frac_bsdf))
            mis /= self.emitter_samples
            L = dr.select(active_e, L + mis * bsdf_val * em_weight, L)

        # ------------------------ BSDF sampling -------------------------
        for _ in range(self.bsdf_samples):
            # Drawn in the order of Mitsuba 3.9's compiled `direct` (whose C++
            # evaluates these call arguments right to left): equal seeds give
            # equal images.
            sample_2 = sampler.next_2d(active)
            sample_1 = sampler.next_1d(active)
            bs, bsdf_weight = bsdf.sample(bsdf_ctx, si, sample_1, sample_2, active)
            active_b = active & dr.any(bsdf_weight != 0)
            si_b = ray_intersect(scene, si.spawn_ray(si.to_world(bs.wo)), active_b)
            emitter = si_b.emitter(scene, active_b)
            active_b &= emitter != None  # noqa: E711
            Le = emitter.eval(si_b, active_b)
            ds = mi.DirectionSample3f(scene, si=si_b, ref=si)
            delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
            em_pdf = dr.select(delta, 0.0, pdf_emitter_direction(scene, si, ds, active_b))
            mis = mis_weight(bs.pdf * self.frac_bsdf, em_pdf * self.frac_em) / self.bsdf_samples
            L = dr.select(active_b, L + bsdf_weight * Le * mis, L)

        return L, valid_ray, []

    # Mitsuba's render, with the infinite emitters given the scene's current
    # bounds first (:func:`.common.refresh_infinite_emitters`).
    render = frozen.sampling_render

    def aov_names(self):
        return []

    def to_string(self):
        return (f"LGDirectIntegrator[\n  emitter_samples = {self.emitter_samples},\n"
                f"  bsdf_samples = {self.bsdf_samples}\n]")
