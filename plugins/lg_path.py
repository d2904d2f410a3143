"""The ``lg_path`` integrator: Mitsuba's ``path`` for scenes with lgsurfaces."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from . import common, frozen
from .common import (compute_interaction, mis_weight, pdf_emitter_direction, ray_intersect,
                     ray_intersect_preliminary, ray_test, sample_emitter_direction,
                     skip_area_emitters)


class LGPathIntegrator(mi.SamplingIntegrator):
    r"""
    .. _integrator-lg_path:

    Path tracer for implicit surfaces (:monosp:`lg_path`)
    -----------------------------------------------------

    .. pluginparameters::

     * - max_depth
       - |int|
       - Longest path depth (-1: no limit). 1 renders only directly visible
         light sources, 2 direct illumination, and so on. (Default: -1)
     * - rr_depth
       - |int|
       - Path depth from which Russian roulette may end paths. (Default: 5)
     * - hide_emitters
       - |bool|
       - Hide directly visible emitters. (Default: |false|)

    Unidirectional path tracing with next-event estimation, multiple importance
    sampling (power heuristic) and Russian roulette, with the parameters and
    the estimator of Mitsuba's ``path``. It sees native shapes and every
    ``lgsurface`` in the scene, keeping the nearer hit, and its shadow rays
    test both. Participating media are ignored: rendering a scene in which a
    shape or the sensor carries a medium warns, naming them
    (:mod:`.checks`).

    .. tabs::

        .. code-tab:: xml

            <integrator type="lg_path">
                <integer name="max_depth" value="8"/>
            </integrator>

        .. code-tab:: python

            'type': 'lg_path',
            'max_depth': 8
    """

    PLUGIN = "lg_path"                  # the plugin name (:func:`.checks.integrator_name`)
    SEES_LGSURFACES = True              # traces lgsurfaces (:func:`.checks.sees_lgsurfaces`)

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        common.read_depths(self, props)

    @dr.syntax
    def sample(self, scene: mi.Scene, sampler: mi.Sampler, ray: mi.RayDifferential3f,
               medium: mi.Medium = None, active: mi.Bool = True):
        if dr.hint(self.max_depth == 0, mode="scalar"):
            return mi.Spectrum(0), mi.Bool(False), []
        bsdf_ctx = mi.BSDFContext()

        # --------------------- Configure loop state ----------------------
        ray = mi.Ray3f(ray)                                  # Current ray
        β = mi.Spectrum(1)                                   # Path throughput
        L = mi.Spectrum(0)                                   # Radiance
        η = mi.Float(1)                                      # Relative IOR
        depth = mi.UInt32(0)                                 # Vertex depth
        valid_ray = mi.Bool(not self.hide_emitters           # Alpha
                            and scene.environment() is not None)
        prev_si = dr.zeros(mi.Interaction3f)                 # Previous vertex
        prev_bsdf_pdf = mi.Float(1)                          # and its BSDF pdf,
        prev_bsdf_delta = mi.Bool(True)                      # delta BSDF?
        active = mi.Bool(active)                             # Active lanes
        hit = ray_intersect_preliminary(scene, ray, active)
        if dr.hint(self.hide_emitters, mode="scalar"):
            ray, hit = skip_area_emitters(scene, ray, hit, active)
        si = compute_interaction(scene, ray, hit, active=active)    # Current vertex

        while dr.hint(active, max_iterations=self.max_depth, label="lg_path"):
            bsdf = si.bsdf(ray)

            # ---------------------- Direct emission ----------------------
            ds = mi.DirectionSample3f(scene, si=si, ref=prev_si)
            em_pdf = dr.select(prev_bsdf_delta, 0.0,
                               pdf_emitter_direction(scene, prev_si, ds, ~prev_bsdf_delta))
            Le = ds.emitter.eval(si, prev_bsdf_pdf > 0)
            L = dr.fma(β, Le * mis_weight(prev_bsdf_pdf, em_pdf), L)

            active_next = (depth + 1 < self.max_depth) & si.is_valid()

            # ---------------------- Emitter sampling ----------------------
            active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
            ds, em_weight, tested = sample_emitter_direction(scene, si, sampler.next_2d(),
                                                             active_em)
            active_em &= ds.pdf != 0
            active_em &= ~ray_test(scene, si.spawn_ray_to(ds.p), active_em & ~tested)
            wo = si.to_local(ds.d)

            # ------ Evaluate BSDF * cos(theta) and sample a direction ------
            sample_1, sample_2 = sampler.next_1d(), sampler.next_2d()
            bsdf_val, bsdf_pdf, bs, bsdf_weight = bsdf.eval_pdf_sample(
                bsdf_ctx, si, wo, sample_1, sample_2, active_next)

            # --------------- Emitter sampling contribution ----------------
            mis_em = dr.select(ds.delta, 1.0, mis_weight(ds.pdf, bsdf_pdf))
            L = dr.select(active_em, dr.fma(β, bsdf_val * em_weight * mis_em, L), L)

            # ---------------------- BSDF sampling ----------------------
            ray = si.spawn_ray(si.to_world(bs.wo))
            β *= bsdf_weight
            η *= bs.eta
            valid_ray |= active & si.is_valid() & ~mi.has_flag(bs.sampled_type, mi.BSDFFlags.Null)

            prev_si = mi.Interaction3f(si)
            prev_bsdf_pdf = bs.pdf
            prev_bsdf_delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)

            # -------------------- Stopping criterion ---------------------
            depth[si.is_valid()] += 1
            β_max = dr.max(β)
            rr_prob = dr.minimum(β_max * η * η, 0.95)
            rr_active = depth >= self.rr_depth
            rr_continue = sampler.next_1d() < rr_prob
            β[rr_active] *= dr.rcp(rr_prob)
            active = active_next & (~rr_active | rr_continue) & (β_max != 0)

            si = ray_intersect(scene, ray, active)

        return dr.select(valid_ray, L, 0), valid_ray, []

    # Mitsuba's render, with the infinite emitters given the scene's current
    # bounds first (:func:`.common.refresh_infinite_emitters`).
    render = frozen.sampling_render

    def aov_names(self):
        return []

    def to_string(self):
        return common.describe_depths(self)
