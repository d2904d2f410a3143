"""The ``lg_prbvolpath`` integrator: path replay backpropagation through
participating media for scenes with lgsurfaces (the estimator of
``lg_volpath``, differentiated as Mitsuba's ``prbvolpath`` does)."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
from mitsuba.ad.integrators.common import RBIntegrator

from lgshape.trace import collection_paused

from . import common, frozen
from .common import (mis_weight, pdf_emitter_direction, ray_intersect,
                     ray_intersect_preliminary, sample_emitter_direction, skip_area_emitters)
from .lg_volpath import _channel_value, _grad_enabled


def _node_kind(params, key):
    """The kind of scene object that holds ``params[key]``: 'shape' (a
    native one), 'sensor', or None (lgsurfaces, media, BSDFs, emitters,
    textures, volumes)."""
    try:
        node = params.properties[key][2]
    except Exception:
        return None
    if getattr(node, "IS_LGSURFACE", False):
        return None                 # (:meth:`LGPRBVolpathIntegrator._why_not` decides)
    if isinstance(node, mi.Shape):
        return "shape"
    if isinstance(node, mi.Sensor):
        return "sensor"
    return None


def uncovered_parameters(params):
    """The gradient-enabled keys of ``params`` that lg_prbvolpath does not
    differentiate: those of native shapes and sensors (lgsurfaces are
    checked one by one: :meth:`LGPRBVolpathIntegrator._why_not`)."""
    if params is None:
        return []
    return [k for k in params.keys() if _grad_enabled(params[k])
            and _node_kind(params, k) is not None]


def _moving(scene):
    """The scene indices of the lgsurfaces whose parameters have gradients
    (asked with gradients resumed: the replay runs with them suspended)."""
    with dr.resume_grad():
        return [k for k, shape in enumerate(common.lg_shapes(scene)) if shape.gradient_keys()]


def _lg_index(scene, moving, shape):
    """k + 1 where ``shape`` is moving lgsurface k, else 0."""
    lgs = common.lg_shapes(scene)
    out = mi.UInt32(0)
    for k in moving:
        out = dr.select(shape == lgs[k]._shape_ptr(), k + 1, out)
    return out


def _shift(scene, moving, index, p, d, active):
    """How far a hit at ``p`` on moving lgsurface ``index`` - 1 (0: none)
    moves along ``d``: zero-valued, with the derivative of
    :meth:`.lgsurface.LGSurface.hit_shift`."""
    lgs = common.lg_shapes(scene)
    out = mi.Float(0)
    for k in moving:
        mine = active & (index == k + 1)
        out = dr.select(mine, lgs[k].hit_shift(p, d, mine), out)
    return out


def _sigma_t(medium, ray, active):
    """The extinction of ``medium`` at the ray's origin (detached): a
    homogeneous medium's, the same everywhere."""
    mei = dr.zeros(mi.MediumInteraction3f)
    mei.p = mi.Point3f(dr.detach(ray.o))
    mei.wavelengths = ray.wavelengths
    mei.medium = medium
    with dr.suspend_grad():
        return dr.detach(medium.get_scattering_coefficients(mei, active)[2])


class LGPRBVolpathIntegrator(RBIntegrator):
    r"""
    .. _integrator-lg_prbvolpath:

    Differentiable volumetric path tracer for implicit surfaces (:monosp:`lg_prbvolpath`)
    -------------------------------------------------------------------------------------

    .. pluginparameters::

     * - max_depth
       - |int|
       - Longest path depth (-1: no limit). (Default: -1)
     * - rr_depth
       - |int|
       - Path depth from which Russian roulette may end paths. (Default: 5)
     * - medium_band
       - |float|
       - Width of the band at each end of a medium segment bounded by a
         moving lgsurface over which the scattering at that end is
         estimated, in mean free paths, at most that fraction of the
         smallest moving lgsurface's bounding radius (0: that term off).
         (Default: 0.1)
     * - hide_emitters
       - |bool|
       - Hide directly visible emitters. (Default: |false|)

    The primal estimate is ``lg_volpath``'s (free-flight sampling in a
    colour channel chosen per path, null collisions in heterogeneous media,
    phase and BSDF sampling, next-event estimation with the transmittance of
    the shadow path through media and ``null`` surfaces, MIS), over native
    shapes and lgsurfaces alike. Gradients are computed by path replay
    (reverse mode, ``dr.backward``): the second pass replays each path with
    the same samples and backpropagates, at each vertex, the radiance that
    follows it times the derivative of that vertex's weight: free-flight
    weight (transmittance over its pdf, with the pdf detached), the
    scattering weight ``sigma_s`` (``sigma_n`` at null collisions), the
    phase function and BSDF values, emission, and, along each shadow path,
    the transmittance of each homogeneous segment and each ratio-tracking
    weight (replayed with a copy of the sampler).

    Differentiates: media parameters (``sigma_t``, ``albedo``, ``scale`` of
    homogeneous media; grid values of heterogeneous ones, as prbvolpath),
    BSDF parameters, phase-function and emitter parameters, and the shape
    (parameters, ``to_world``) of an lgsurface with a ``null`` BSDF whose
    media are homogeneous (:meth:`_moving_ends`: the image is continuous
    across such a surface's silhouettes, so it has interior terms only).
    It does *not* differentiate other shapes (lgsurfaces with another BSDF,
    emitting or next to a heterogeneous medium; native shapes) nor the
    sensor: a gradient enabled on one raises
    :class:`~.checks.NotDifferentiableError` naming it. Forward mode
    (``dr.forward``) is refused likewise. The camera rays start outside
    any medium (a sensor's own medium is ignored, as in prbvolpath).
    """

    PLUGIN = "lg_prbvolpath"            # the plugin name (:func:`.checks.integrator_name`)
    SEES_LGSURFACES = True              # traces lgsurfaces (:func:`.checks.sees_lgsurfaces`)
    DIFFERENTIATES_LGSURFACES = True    # (those :meth:`_why_not` allows; the rest raise)

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        common.read_depths(self, props)
        self.medium_band = props.get("medium_band", 0.1)
        if not self.medium_band >= 0:
            raise ValueError(f"lg_prbvolpath: 'medium_band' must be >= 0, got {self.medium_band}")

    # ---- Checks -------------------------------------------------------------

    def _refuse_uncovered(self, scene, params):
        from .checks import NotDifferentiableError
        keys = uncovered_parameters(params)
        if keys:
            names = ", ".join(f"'{k}'" for k in keys)
            raise NotDifferentiableError(
                f"lg_prbvolpath differentiates media, BSDF, phase and emitter parameters and the "
                f"shapes of lgsurfaces that bound homogeneous media with a 'null' BSDF, but a "
                f"gradient was asked for the shape or sensor parameters {names}: 'lg_prb' gives "
                f"shape gradients with the media left out, or call dr.disable_grad() on them")
        self.refuse_uncovered_lgsurfaces(scene)

    def refuse_uncovered_lgsurfaces(self, scene):
        """Raise :class:`~.checks.NotDifferentiableError` where an lgsurface
        whose shape this integrator cannot differentiate (:meth:`_why_not`)
        has gradients enabled (called by :func:`.checks.check_gradients`
        before each render)."""
        from .checks import NotDifferentiableError
        for shape in common.lg_shapes(scene):
            with dr.resume_grad():          # (a primal render runs with them suspended)
                keys = shape.gradient_keys()
            why = self._why_not(shape) if keys else None
            if why:
                names = ", ".join(f"'{k}'" for k in keys)
                raise NotDifferentiableError(
                    f"lg_prbvolpath differentiates an lgsurface's shape only where it bounds "
                    f"homogeneous media with a 'null' BSDF (the image is then continuous across "
                    f"its silhouettes), but gradients are enabled on {names} and {why}: 'lg_prb' "
                    f"differentiates it with the media left out, or call dr.disable_grad() on "
                    f"them")

    @staticmethod
    def _why_not(shape):
        """Why lg_prbvolpath cannot differentiate this moving lgsurface's
        shape (None where it can)."""
        bsdf = shape.bsdf()
        lobes = int(mi.BSDFFlags.All) & ~int(mi.BSDFFlags.Null)
        if bsdf is None or int(bsdf.flags()) & lobes:
            return "its BSDF is not 'null' (its silhouettes and shadow edges are not covered here)"
        if shape.emitter() is not None:
            return "it is an area emitter"
        for side, medium in (("interior", shape.interior_medium()),
                             ("exterior", shape.exterior_medium())):
            if medium is not None and not medium.is_homogeneous():
                return f"its {side} medium is heterogeneous"
        return None

    @collection_paused()
    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        common.check(self, scene, sensor)
        return frozen.render(self, RBIntegrator.render, scene, sensor, seed, spp,
                             develop, evaluate)

    def render_forward(self, scene, params, sensor=0, seed=0, spp=0):
        from .checks import NotDifferentiableError
        common.check(self, scene, sensor)
        self._refuse_uncovered(scene, params)
        on = [k for k in (params.keys() if params is not None else []) if _grad_enabled(params[k])]
        raise NotDifferentiableError(
            f"lg_prbvolpath computes gradients in reverse mode only (dr.backward), but a "
            f"forward-mode gradient was asked for {', '.join(repr(k) for k in on) or '(none)'}: "
            f"use dr.backward, or dr.forward with Mitsuba's 'prb' / lgshape's 'lg_prb' for "
            f"scenes without media")

    @collection_paused()
    def render_backward(self, scene, params, grad_in, sensor=0, seed=0, spp=0):
        common.check(self, scene, sensor)
        self._refuse_uncovered(scene, params)
        with common.traced_searches(scene):
            super().render_backward(scene, params, grad_in, sensor, seed, spp)

    # ---- The path -----------------------------------------------------------

    @dr.syntax
    def sample(self, mode: dr.ADMode, scene: mi.Scene, sampler: mi.Sampler, ray: mi.Ray3f,
               δL=None, state_in=None, active=True, **kwargs):
        primal = mode == dr.ADMode.Primal
        if dr.hint(self.max_depth == 0, mode="scalar"):
            return mi.Spectrum(0), mi.Bool(False), [], mi.Spectrum(0)
        ray = mi.Ray3f(dr.detach(ray))
        active = mi.Bool(active)
        L = mi.Spectrum(0 if primal else state_in)     # primal: sum; replay: what is left
        δL = mi.Spectrum(δL if δL is not None else 0)
        throughput = mi.Spectrum(1)
        η = mi.Float(1)
        depth = mi.UInt32(0)
        medium = dr.zeros(mi.MediumPtr)
        channel = mi.UInt32(0)
        if dr.hint(dr.size_v(mi.Spectrum) > 1, mode="scalar"):
            n = dr.size_v(mi.Spectrum)
            channel = mi.UInt32(dr.minimum(n * sampler.next_1d(active), n - 1))
        si = dr.zeros(mi.SurfaceInteraction3f)
        needs_intersection = mi.Bool(True)
        last_event = dr.zeros(mi.Interaction3f)
        last_pdf = mi.Float(1)
        specular_chain = mi.Bool(True)
        valid_ray = mi.Bool(False)
        bsdf_ctx = mi.BSDFContext()
        moving = [] if primal else _moving(scene)
        entry = mi.UInt32(0)        # k + 1: the ray starts where it crossed moving lgsurface k
        if dr.hint(self.hide_emitters, mode="scalar"):
            hit = ray_intersect_preliminary(scene, ray, active)
            ray, hit = skip_area_emitters(scene, ray, hit, active)
            si = common.compute_interaction(scene, ray, hit, active=active)
            needs_intersection = mi.Bool(False)

        while dr.hint(active, max_iterations=-1, label=f"lg_prbvolpath ({mode.name})"):
            # ---------------- Russian roulette ----------------
            q = dr.minimum(dr.max(throughput) * η * η, 0.95)
            rr = depth >= self.rr_depth
            active &= ~rr | (sampler.next_1d(active) < q)
            throughput[rr] *= dr.rcp(q)
            active &= dr.any(throughput != 0)

            with dr.resume_grad(when=not primal):
                # ---------------- Free flight in a medium ----------------
                in_medium = active & (medium != None)  # noqa: E711
                mei = medium.sample_interaction(ray, sampler.next_1d(in_medium), channel,
                                                in_medium)
                mei.t = dr.detach(mei.t)
                ray.maxt[in_medium & medium.is_homogeneous() & mei.is_valid()] = mei.t
                fresh = in_medium & needs_intersection
                si[fresh] = dr.detach(ray_intersect(scene, ray, fresh))
                needs_intersection &= ~in_medium
                mei.t[in_medium & (si.t < mei.t)] = dr.inf
                tr, ff_pdf = medium.transmittance_eval_pdf(mei, si, in_medium)
                tr_pdf = dr.detach(_channel_value(ff_pdf, channel))
                weight = mi.Spectrum(1)
                weight[in_medium] = dr.select(tr_pdf > 0, tr / tr_pdf, 0.0)
                escaped = in_medium & ~mei.is_valid()
                if dr.hint(bool(moving), mode="scalar"):
                    weight *= self._moving_ends(scene, moving, ray, si, mei, entry, in_medium,
                                                escaped, medium, δL, L)
                in_medium &= mei.is_valid()

                # null collision (heterogeneous media) or real scattering
                scatter_p = dr.detach(_channel_value(mei.sigma_t, channel) /
                                      _channel_value(mei.combined_extinction, channel))
                null = in_medium & ~medium.is_homogeneous() & \
                    (sampler.next_1d(in_medium) >= scatter_p)
                scatter = in_medium & ~null
                weight[null] *= mei.sigma_n / (1 - scatter_p)
                weight[scatter & ~medium.is_homogeneous()] *= mei.sigma_s / scatter_p
                weight[scatter & medium.is_homogeneous()] *= mei.sigma_s
                throughput *= dr.detach(weight)
                if dr.hint(not primal and dr.grad_enabled(weight), mode="scalar"):
                    after = dr.detach(dr.select(in_medium | escaped,
                                                L / dr.maximum(1e-8, weight), 0.0))
                    dr.backward_from(δL * weight * after)
                mei = dr.detach(mei)
            ray.o[null] = mei.p
            entry[null] = 0
            si.t[null] = si.t - mei.t
            depth[scatter] += 1
            active &= depth < self.max_depth
            scatter &= active
            phase_ctx = mi.PhaseFunctionContext(sampler)
            phase = mei.medium.phase_function()
            phase[~scatter] = dr.zeros(mi.PhaseFunctionPtr)

            # ---------------- Surfaces: intersection and emission ----------------
            on_surface = active & ~in_medium & (escaped | (medium == None))  # noqa: E711
            fresh = on_surface & needs_intersection
            si[fresh] = dr.detach(ray_intersect(scene, ray, fresh))
            needs_intersection &= ~on_surface
            with dr.resume_grad(when=not primal):
                emitter = si.emitter(scene)
                seen = on_surface & (emitter != None) & \
                    ~((depth == 0) & self.hide_emitters)  # noqa: E711
                ds_e = mi.DirectionSample3f(scene, si, last_event)
                em_pdf = pdf_emitter_direction(scene, last_event, ds_e, seen & ~specular_chain)
                direct = specular_chain | (depth == 0)
                contrib = throughput * emitter.eval(si, seen) * \
                    dr.select(direct, 1.0, mis_weight(last_pdf, em_pdf))
                L[seen] += dr.detach(contrib if primal else -contrib)
                if dr.hint(not primal and dr.grad_enabled(contrib), mode="scalar"):
                    dr.backward_from(δL * dr.select(seen, contrib, 0.0))
            on_surface &= si.is_valid()
            bsdf = si.bsdf(ray)

            # ---------------- Next-event estimation (medium or surface) ----------------
            nee_m = scatter & mei.medium.use_emitter_sampling()
            specular_chain &= ~scatter
            specular_chain |= scatter & ~mei.medium.use_emitter_sampling()
            nee_s = on_surface & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth) & \
                (depth + 1 < self.max_depth)
            nee = nee_m | nee_s
            ref = dr.zeros(mi.Interaction3f)
            ref[nee_m] = mei
            ref[nee_s] = mi.Interaction3f(si)
            nee_sampler = sampler if primal else sampler.clone()
            emitted, ds = self._direct(scene, sampler, ref, si, nee_m, nee_s, medium, channel)
            with dr.resume_grad(when=not primal):
                b_val, b_pdf = bsdf.eval_pdf(bsdf_ctx, si, si.to_local(ds.d), nee_s)
                p_val, p_pdf = phase.eval_pdf(phase_ctx, mei, ds.d, nee_m)
                f_val = dr.select(nee_s, b_val, p_val)
                f_pdf = dr.select(ds.delta, 0.0, dr.select(nee_s, b_pdf, p_pdf))
                contrib = throughput * f_val * emitted * mis_weight(ds.pdf, dr.detach(f_pdf))
                L[nee] += dr.detach(contrib if primal else -contrib)
                if dr.hint(not primal, mode="scalar"):
                    # the shadow path's transmittance, replayed (in its loop)
                    self._direct(scene, nee_sampler, ref, si, nee_m, nee_s, medium, channel,
                                 adjoint=dr.detach(dr.select(nee, contrib, 0.0)) * δL)
                    if dr.hint(dr.grad_enabled(contrib), mode="scalar"):
                        dr.backward_from(δL * dr.select(nee, contrib, 0.0))

            # ---------------- Phase sampling ----------------
            valid_ray |= scatter
            with dr.suspend_grad():
                wo, p_weight, p_pdf = phase.sample(phase_ctx, mei, sampler.next_1d(scatter),
                                                   sampler.next_2d(scatter), scatter)
            scatter &= p_pdf > 0
            if dr.hint(not primal, mode="scalar"):
                with dr.resume_grad():
                    p_eval, _ = phase.eval_pdf(phase_ctx, mei, wo, scatter)
                    if dr.hint(dr.grad_enabled(p_eval), mode="scalar"):
                        after = dr.detach(dr.select(scatter, L / dr.maximum(1e-8, p_eval), 0.0))
                        dr.backward_from(δL * p_eval * after)
            throughput[scatter] *= p_weight
            ray[scatter] = mei.spawn_ray(wo)
            entry[scatter] = 0
            needs_intersection |= scatter
            last_event[scatter] = mei
            last_pdf[scatter] = p_pdf

            # ---------------- BSDF sampling ----------------
            with dr.suspend_grad():
                bs, b_weight = bsdf.sample(bsdf_ctx, si, sampler.next_1d(on_surface),
                                           sampler.next_2d(on_surface), on_surface)
            on_surface &= bs.pdf > 0
            if dr.hint(not primal, mode="scalar"):
                with dr.resume_grad():
                    b_eval = bsdf.eval(bsdf_ctx, si, bs.wo, on_surface)
                    if dr.hint(dr.grad_enabled(b_eval), mode="scalar"):
                        after = dr.detach(dr.select(on_surface,
                                                    L / dr.maximum(1e-8, b_eval), 0.0))
                        dr.backward_from(δL * b_eval * after)
            throughput[on_surface] *= b_weight
            η[on_surface] *= bs.eta
            ray[on_surface] = si.spawn_ray(si.to_world(bs.wo))
            entry[on_surface] = _lg_index(scene, moving, si.shape) if moving else 0
            needs_intersection |= on_surface
            real = on_surface & ~mi.has_flag(bs.sampled_type, mi.BSDFFlags.Null)
            depth[real] += 1
            valid_ray |= real
            last_event[real] = si
            last_pdf[real] = bs.pdf
            specular_chain |= real & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
            specular_chain &= ~(real & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Smooth))
            crossing = on_surface & si.is_medium_transition()
            medium[crossing] = si.target_medium(ray.d)
            active &= in_medium | on_surface

        return (L if primal else δL), valid_ray, [], L

    def _moving_ends(self, scene, moving, ray, si, mei, entry, in_medium, escaped, medium,
                     δL, L):
        """The derivatives of a free flight in a homogeneous medium whose
        segment starts or ends on a moving lgsurface (``moving``: their scene
        indices), where it crosses (a 'null' boundary): the factor
        exp(sigma_t (da - db)) that the flight's weight takes (its value 1;
        da, db: how far the segment's start, where the ray crossed moving
        lgsurface ``entry`` - 1, and its end, ``si`` on the lanes that pass
        the segment, move along the ray), and, backpropagated here, the
        scattering at the ends: a segment [a, b] moves the image by
        T(b) sigma_s L_i(b) db - sigma_s L_i(a) da besides, whose densities
        are estimated from this flight's own collisions near each end
        (within ``medium_band`` mean free paths, at most that part of the
        smallest moving surface's bounding radius), weighted by
        :func:`.lgsurface.edge_weight` (first moment 0) times what the path
        brings from the collision on (``L``, what is left to replay)."""
        from .lgsurface import edge_weight
        lgs = common.lg_shapes(scene)
        sigma = _sigma_t(medium, ray, in_medium)
        d_a = _shift(scene, moving, entry, ray.o, ray.d, in_medium)
        d_b = _shift(scene, moving, _lg_index(scene, moving, si.shape), ray(si.t), ray.d, escaped)
        factor = dr.exp(sigma * (d_a - dr.select(escaped, d_b, 0.0)))
        if dr.hint(self.medium_band > 0, mode="scalar"):
            radius = min(float(lgs[k]._sphere[1]) for k in moving)
            h = self.medium_band * dr.minimum(dr.rcp(dr.max(dr.detach(sigma))), radius)
            event = in_medium & mei.is_valid()
            t = dr.detach(mei.t)
            w_a = dr.select(event & (entry != 0), edge_weight(-t, h), 0.0)
            probe = mi.Ray3f(dr.detach(ray))
            probe.o = mi.Point3f(ray(t))
            probe.maxt = h
            hit = ray_intersect_preliminary(scene, probe, event)
            near = event & hit.is_valid()
            w_b = dr.select(near, edge_weight(-hit.t, h), 0.0)
            d_end = _shift(scene, moving, hit.lg, probe(hit.t), probe.d, near & (w_b != 0))
            # (d_a again: a backward pass frees the graph of what it traverses,
            # and the flight's weight still holds d_a)
            d_a = _shift(scene, moving, entry, ray.o, ray.d, event & (w_a != 0))
            term = w_b * d_end - w_a * d_a
            dr.backward_from(δL * dr.detach(dr.select(event, L, 0.0)) * term)
        return dr.select(in_medium, factor, 1.0)

    @dr.syntax
    def _direct(self, scene, sampler, ref, si, from_medium, from_surface, medium, channel,
                adjoint=None):
        """An emitter sample from ``ref`` (a medium event, or the surface
        ``si``) with the transmittance of its shadow path, as lg_volpath's:
        (emitted * tr / pdf, ds), detached. With ``adjoint`` (the adjoint
        radiance times the detached contribution of this sample), it also
        backpropagates ``adjoint * d log(mult)`` for each factor ``mult`` of
        the transmittance (homogeneous segments in closed form, ratio
        tracking's sigma_n / sigma_bar), inside the loop."""
        replay = adjoint is not None
        active = mi.Bool(from_medium | from_surface)
        with dr.suspend_grad():
            ds, emitted, _ = sample_emitter_direction(scene, ref, sampler.next_2d(active),
                                                      active, through_null=True)
        active &= ds.pdf != 0
        emitted[~active] = 0.0
        medium = dr.select(active, medium, dr.zeros(mi.MediumPtr))
        medium[from_surface & si.is_medium_transition()] = si.target_medium(ds.d)
        ray = ref.spawn_ray_to(ds.p)
        max_dist = mi.Float(ray.maxt)
        total = mi.Float(0)
        tr = mi.Spectrum(1)
        s = dr.zeros(mi.SurfaceInteraction3f)
        needs_intersection = mi.Bool(True)
        moving = _moving(scene) if replay else []
        entry = mi.UInt32(0)
        while dr.hint(active, max_iterations=-1, label="lg_prbvolpath: shadow path"):
            remaining = max_dist - total
            ray.maxt = remaining
            active &= remaining > 0
            fresh = active & needs_intersection
            s[fresh] = dr.detach(ray_intersect(scene, ray, fresh))
            needs_intersection &= False
            with dr.resume_grad(when=replay):
                in_medium = active & (medium != None)  # noqa: E711
                mei = medium.sample_interaction(ray, sampler.next_1d(in_medium), channel,
                                                in_medium)
                mei.t = dr.detach(mei.t)
                mei.t[in_medium & (s.t < mei.t)] = dr.inf
                homogeneous = in_medium & medium.is_homogeneous()
                mult = mi.Spectrum(1)
                mei.t[homogeneous] = dr.minimum(remaining, s.t)
                mult[homogeneous] = medium.transmittance_eval_pdf(mei, s, homogeneous)[0]
                if dr.hint(bool(moving), mode="scalar"):
                    ends = homogeneous & (s.t < remaining)
                    shift = _shift(scene, moving, entry, ray.o, ray.d, homogeneous) - \
                        _shift(scene, moving, _lg_index(scene, moving, s.shape), ray(s.t), ray.d,
                               ends)
                    mult[homogeneous] *= dr.exp(_sigma_t(medium, ray, homogeneous) * shift)
                mei.t[homogeneous] = dr.inf
                escaped = in_medium & ~mei.is_valid()
                in_medium &= mei.is_valid()
                ray.o[in_medium] = dr.detach(mei.p)
                s.t[in_medium] = s.t - mei.t
                mult[in_medium] *= mei.sigma_n / mei.combined_extinction
                if dr.hint(replay, mode="scalar"):
                    if dr.hint(dr.grad_enabled(mult), mode="scalar"):
                        dr.backward_from(adjoint * mult / dr.maximum(1e-8, dr.detach(mult)))
                mult = dr.detach(mult)
            on_surface = (active & (medium == None) | escaped) & s.is_valid() & \
                ~in_medium  # noqa: E711
            bsdf = s.bsdf(ray)
            mult[on_surface] *= bsdf.eval_null_transmission(s, on_surface)
            tr *= mult
            ray[on_surface] = s.spawn_ray(mi.Vector3f(ray.d))
            entry[in_medium] = 0
            entry[on_surface] = _lg_index(scene, moving, s.shape) if moving else 0
            ray.maxt = remaining
            needs_intersection |= on_surface
            active &= (in_medium | on_surface) & dr.any(tr != 0)
            total[active] += dr.select(in_medium, mei.t, s.t)
            medium[on_surface & s.is_medium_transition()] = s.target_medium(ray.d)
        return dr.detach(emitted * tr), dr.detach(ds)

    def aov_names(self):
        return []

    def to_string(self):
        return common.describe_depths(self)
