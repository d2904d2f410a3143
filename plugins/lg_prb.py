"""The ``lg_prb`` integrator: path replay backpropagation (Mitsuba's ``prb``)
for scenes with lgsurfaces."""
from __future__ import annotations

import contextlib

import drjit as dr
import mitsuba as mi
from mitsuba.python.ad.integrators.common import RBIntegrator, solid_angle_to_area_jacobian

from lgshape.trace import collection_paused

from . import common, frozen
from .common import (Hit, compute_interaction, mis_weight, pdf_emitter_direction,
                     ray_intersect_preliminary, ray_test, sample_emitter_direction,
                     skip_area_emitters)


@contextlib.contextmanager
def _unwrapped():
    """Within it, an exception whose cause chain holds a
    :class:`~.checks.NotDifferentiableError` (Dr.Jit's loops raise
    ``RuntimeError: dr.while_loop(): encountered an exception`` from it)
    is raised as that error."""
    from .checks import NotDifferentiableError
    try:
        yield
    except NotDifferentiableError:
        raise
    except Exception as err:
        cause, seen = err.__cause__ or err.__context__, set()
        while cause is not None and id(cause) not in seen:
            if isinstance(cause, NotDifferentiableError):
                raise cause from None
            seen.add(id(cause))
            cause = cause.__cause__ or cause.__context__
        raise


class PathRecord:
    """What lg_prb's primal pass records of each path for the replay, so
    that the replay traces again only what the record does not hold: which
    of the first 32 vertices' emitter samples were unoccluded (``lit``, bit
    i: vertex i), which of those vertices lie on an lgsurface (``on_lg``;
    the camera's hit, vertex 0, is searched again: it is cheap), and the
    surface and distance of the first ``slots`` of those (``ids``, 8 bits a
    surface: scene index + 1; ``ts``), with ``count`` the lgsurface vertices
    so far. Its size is fixed (at most 8 slots), not the path's length.

    The state is a tuple (lit, on_lg, ids, ts, count) that the loop
    carries. Where the integrator's max_depth bounds every path within the
    record (``complete``), the replay holds no shadow test and no lgsurface
    search at all."""

    MAX_SLOTS = 8

    def __init__(self, max_depth, n_lgsurfaces):
        bounded = 0 < max_depth <= 32
        # vertices 1 .. max_depth - 1 may lie on lgsurfaces
        self.slots = min(max_depth - 1, self.MAX_SLOTS) if bounded else 4
        self.slots = max(self.slots, 1)
        self.keep_hits = n_lgsurfaces < 256
        self.all_lit = bounded
        self.complete = bounded and self.keep_hits and max_depth - 1 <= self.slots

    def new(self):
        """The empty record."""
        n_ids = (self.slots + 3) // 4
        return (mi.UInt32(0), mi.UInt32(0), tuple(mi.UInt32(0) for _ in range(n_ids)),
                tuple(mi.Float(dr.inf) for _ in range(self.slots)), mi.UInt32(0))

    @staticmethod
    def resumed(state):
        """The record handed over by the primal pass, its count restarted."""
        return (*state[:4], mi.UInt32(0))

    @staticmethod
    def handed_over(state):
        """The part of the record the replay needs."""
        return state[:4]

    @staticmethod
    def _bit(vertex):
        """Vertex ``vertex``'s bit in the masks (none from 32 on)."""
        return dr.select(vertex < 32, mi.UInt32(1) << dr.minimum(vertex, 31), 0)

    def visibility(self, scene, ray, active, tested, primal, state, vertex):
        """The emitter sample's visibility (``active`` where its shadow ray
        ``ray`` is unoccluded; ``tested`` lanes are known already) and the
        record: the primal pass tests and records it, the replay takes it
        from the record (testing only from vertex 32 on)."""
        lit, *rest = state
        if primal:
            active = active & ~ray_test(scene, ray, active & ~tested)
            return active, (lit | dr.select(active, self._bit(vertex), 0), *rest)
        recorded = (lit & self._bit(vertex)) != 0
        if self.all_lit:
            return active & recorded, state
        known = vertex < 32
        occluded = ray_test(scene, ray, active & ~tested & ~known)
        return active & dr.select(known, recorded, ~occluded), state

    def add(self, state, vertex, hit):
        """The primal pass: the record with ``hit`` (vertex ``vertex``)
        added where it is on an lgsurface."""
        lit, on_lg, ids, ts, count = state
        on = (vertex < 32) & (hit.lg != 0)
        on_lg = on_lg | dr.select(on, self._bit(vertex), 0)
        if self.keep_hits:
            ts = tuple(dr.select(on & (count == j), hit.t, t) for j, t in enumerate(ts))
            ids = tuple(v | dr.select(on & (count >= 4 * i) & (count < min(4 * i + 4, self.slots)),
                                      hit.lg << (8 * ((count - 4 * i) & 3)), 0)
                        for i, v in enumerate(ids))
        return lit, on_lg, ids, ts, count + dr.select(on, 1, 0)

    def replayed_hit(self, scene, ray, active, state, vertex):
        """The replay's hit along ``ray`` (vertex ``vertex``: the primal
        pass's hit there, along the same ray) and the record with its count
        advanced: taken from the record where it holds it, searched among
        the native shapes only where the primal pass found no lgsurface,
        searched fully beyond what the record holds."""
        lit, on_lg, ids, ts, count = state
        on = (on_lg & self._bit(vertex)) != 0
        if not self.keep_hits:
            hit = ray_intersect_preliminary(scene, ray, active, on | (vertex >= 32))
            return hit, state
        kept = on & (count < self.slots)
        search = False if self.complete else on | (vertex >= 32)
        hit = ray_intersect_preliminary(scene, ray, active & ~kept, search)
        t, word = ts[0], ids[0]
        for j in range(1, self.slots):
            t = dr.select(count == j, ts[j], t)
        for i in range(1, len(ids)):
            word = dr.select(count >= 4 * i, ids[i], word)
        lg = (word >> (8 * (count & 3))) & 0xFF
        hit = Hit(pi=dr.select(kept, dr.zeros(mi.PreliminaryIntersection3f), hit.pi),
                  lg=dr.select(kept, lg, hit.lg), t=dr.select(kept, t, hit.t))
        return hit, (lit, on_lg, ids, ts, count + dr.select(on, 1, 0))


def _lg_name(lgs, k):
    """The scene's k-th lgsurface as a message names it."""
    if lgs[k].id():
        return f"'{lgs[k].id()}'"
    return f"{k + 1} of {len(lgs)} (no id)"


def _shape_names(scene, shapes, most=3):
    names = [f"'{s.id()}'" if s.id() else s.class_name() for s in shapes]
    return ", ".join(names[:most]) + (f" and {len(names) - most} more"
                                      if len(names) > most else "")


def _cut_by_box(shape, cache, n=33):
    """Does f change sign (or vanish) on the faces of ``shape``'s box, so
    that the box cuts the surface (an open surface; its cut edges move with
    ``to_world`` and slide with f's parameters)? f is sampled on an n x n
    grid of each face (so a crossing narrower than the grid's spacing can
    go unseen). ``cache`` keeps the answer per shape for its surface (the
    object a parameter update rebuilds)."""
    surface = shape.surface
    kept = cache.get(shape.ptr)
    if kept is not None and kept[0] is surface:
        return kept[1]
    import numpy as np
    lo, hi = (np.asarray(v, np.float64) for v in surface.bbox)
    u = np.linspace(0.0, 1.0, n)
    a, b = (g.ravel() for g in np.meshgrid(u, u))
    points = []
    for axis in range(3):
        i, j = [x for x in range(3) if x != axis]
        for side in (lo[axis], hi[axis]):
            p = np.empty((a.size, 3))
            p[:, axis] = side
            p[:, i] = lo[i] + a * (hi[i] - lo[i])
            p[:, j] = lo[j] + b * (hi[j] - lo[j])
            points.append(p)
    p = np.concatenate(points).astype(np.float32)
    with dr.suspend_grad():
        f = np.asarray(surface.value(mi.Point3f(p[:, 0], p[:, 1], p[:, 2])), np.float64)
    f = f[np.isfinite(f)]
    cut = bool(f.size and (f.min() <= 0 <= f.max()))
    cache[shape.ptr] = (surface, cut)
    return cut


def _textured_native_emitters(scene):
    """Does a native shape of ``scene`` carry a spatially varying area
    emitter (whose samples lg_prb intersects again, as prb does)?"""
    lg = {e.ptr for s in common.lg_shapes(scene) if (e := s.emitter()) is not None}
    return any(mi.has_flag(e.flags(), mi.EmitterFlags.Surface)
               and mi.has_flag(e.flags(), mi.EmitterFlags.SpatiallyVarying)
               and e.ptr not in lg for e in scene.emitters())


class LGPRBIntegrator(RBIntegrator):
    r"""
    .. _integrator-lg_prb:

    Path replay backpropagation for implicit surfaces (:monosp:`lg_prb`)
    --------------------------------------------------------------------

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
     * - boundary
       - |bool|
       - Add the boundary term of the lgsurfaces' primary silhouettes (the
         visibility gradient of moving silhouettes seen by the camera).
         (Default: |true|)
     * - shadow_edges
       - |bool|
       - Add the boundary term of the shadows that moving lgsurfaces cast
         on the emitter samples (at every vertex; needs ``boundary``).
         (Default: |true|)
     * - band_width
       - |float|
       - Width, in pixels, of the band inside each silhouette over which
         that term is relaxed: its bias grows with the band against the
         silhouette's curvature radius (in pixels), its variance as the band
         narrows. The edges of shadows get twice that, in pixels at the
         shaded point. (Default: 1)
     * - bounce_edges
       - |int|
       - How many bounces of each path add the boundary term of the moving
         lgsurfaces' silhouettes they see (in mirrors, through glass, in
         interreflections; needs ``boundary``). 0 turns it off. (Default: 2)
     * - band_paths
       - |int|
       - How many paths estimate the radiance on each side (L_s, L_b) of
         a silhouette's band sample (the mean of them; traced on the band's
         samples alone, they cost little). (Default: 8)
     * - stratified
       - |bool|
       - Stratify a gradient pass's camera rays over each pixel (jittered
         over a grid of its cells) where it computes boundary terms: the
         fraction of a pixel's samples that fall in a silhouette's band then
         varies far less. False: Mitsuba's camera rays, the samples that
         ``lg_path`` takes at the same seed. (Default: |true|)
     * - light_band
       - |float|
       - Width of the band inside the edges of an emitting lgsurface's
         light (its silhouette, and the shadows that moving lgsurfaces cast
         on it), as a fraction of the light's angular radius seen from each
         shading point: the bias of that term grows with it, its variance
         as it narrows. An emitter thinner than this fraction of its size
         needs a smaller value. (Default: 0.05)

    ``lg_path``'s estimator (emitter sampling, MIS, Russian roulette) as a
    differentiable integrator: ``mi.render(scene, params, ...)``,
    ``dr.backward`` and ``dr.forward`` work as with Mitsuba's ``prb``, whose
    conventions it follows (path replay: the primal pass, then a second pass
    with the same samples that propagates the adjoint radiance vertex by
    vertex, so memory does not grow with the path length). Its primal image
    is ``lg_path``'s: the same samples in the same order. The primal pass
    also hands the replay a fixed-size record of each path (:class:`PathRecord`:
    which of its first 32 emitter samples were unoccluded, which vertices
    lie on lgsurfaces and up to eight of those hits), so that the replay
    repeats no shadow test and no lgsurface search there.

    It differentiates Mitsuba's plugins as ``prb`` does (BSDFs, textures,
    emitters, native shapes' interior derivatives) and an lgsurface's own
    parameters (``to_world`` and every numeric parameter of f): the ray
    search stays detached and each hit is attached to the parameters by the
    implicit-function theorem (:meth:`LGSurface.compute_surface_interaction`),
    so shading, normals, emitter terms and the next bounce carry the
    derivatives. The silhouettes of moving lgsurfaces seen along the
    replay's paths, from the camera and after each of the first
    ``bounce_edges`` bounces (in mirrors, through glass, in
    interreflections), add their boundary term (:meth:`_replay_edges`:
    relaxed over a band of ``band_width`` pixels, on the hits that the
    primal pass records; the gradient pass's camera rays stratified over
    each pixel: :meth:`_stratified_rays`), and so do the shadow edges
    they cast on the emitter samples, at every vertex (:meth:`_shadow_edge`:
    relaxed over twice ``band_width`` pixels at the shaded point, carried to
    the occluder). The light of an emitting lgsurface follows its
    shape: its cone samples are re-attached (:meth:`_cone_sample_interior`)
    and the edge of its light seen from each shading point, its silhouette
    and the shadows moving lgsurfaces cast on it, has its boundary term
    (:meth:`_light_edges`, over ``light_band`` of the light's angular
    radius). Left out: silhouettes seen after more bounces,
    edges where a surface is cut by its box (a gradient pass says so once:
    :meth:`uncovered`), and native shapes' boundaries (``prb`` leaves all
    boundaries out).
    Participating media are ignored (and a scene with some warns).

    .. tabs::

        .. code-tab:: xml

            <integrator type="lg_prb">
                <integer name="max_depth" value="4"/>
            </integrator>

        .. code-tab:: python

            'type': 'lg_prb',
            'max_depth': 4
    """

    PLUGIN = "lg_prb"                   # the plugin name (:func:`.checks.integrator_name`)
    #: The shadow edges' band against a silhouette's (:meth:`_shadow_edge`):
    #: their weight (:func:`.lgsurface.edge_weight`) cancels the band's slope,
    #: so a wider band costs less bias there, and the band on the shading
    #: points is what their variance depends on.
    SHADOW_BAND = 2.0
    #: The delta vertices from the camera (a mirror, glass) whose turn the
    #: replay follows as a moving lgsurface's normal moves (:meth:`_chain_rays`)
    CHAIN = 4
    SEES_LGSURFACES = True              # traces lgsurfaces (:func:`.checks.sees_lgsurfaces`)
    DIFFERENTIATES_LGSURFACES = True    # (:func:`.checks.differentiates_lgsurfaces`)

    def __init__(self, props: mi.Properties):
        super().__init__(props)
        common.read_depths(self, props)
        self.boundary = bool(props.get("boundary", True))
        self.shadow_edges = bool(props.get("shadow_edges", True))
        self.band_width = float(props.get("band_width", 1.0))
        self.light_band = float(props.get("light_band", 0.05))
        self.bounce_edges = int(props.get("bounce_edges", 2))
        self.band_paths = int(props.get("band_paths", 8))
        self.stratified = bool(props.get("stratified", True))
        self._edges = None                  # (moving, seed) in a gradient pass: _edges_on
        self._kept = None                   # what _replay_edges takes from the replay
        self._camera = None                 # the gradient pass's camera samples
        self._pixel = (0.0, 0.0)            # (angle, footprint): _pixel_spread
        self._cut = {}                      # shape -> (surface, cut by its box?): _cut_by_box
        if not self.band_width > 0:
            raise ValueError("lg_prb: 'band_width' must be > 0 (pixels)")
        if self.band_paths < 1:
            raise ValueError("lg_prb: 'band_paths' must be >= 1 (paths per band sample)")
        if self.bounce_edges < 0:
            raise ValueError("lg_prb: 'bounce_edges' must be >= 0 (a number of bounces)")
        if not 0 < self.light_band < 1:
            raise ValueError("lg_prb: 'light_band' must lie in (0, 1) (a fraction of a light's "
                             "angular radius)")

    # Mitsuba's render, forward and backward passes, after the checks (media
    # ignored) and with the infinite emitters given the scene's current
    # bounds (:func:`.common.refresh_infinite_emitters`).
    # A parameter that lg_prb cannot differentiate (a library surface's that
    # f computes with in Python) raises NotDifferentiableError itself: it is
    # checked before tracing (_check_differentiable), and one raised while
    # tracing, which Dr.Jit's loops wrap in a RuntimeError, is unwrapped
    # (_unwrapped).
    @collection_paused()
    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        common.check(self, scene, sensor)
        self._check_differentiable(scene)
        with _unwrapped():
            return frozen.render(self, RBIntegrator.render, scene, sensor,
                                 seed, spp, develop, evaluate)

    @collection_paused()
    def render_forward(self, scene, params, sensor=0, seed=0, spp=0):
        common.check(self, scene, sensor)
        self._check_differentiable(scene)
        self._warn_uncovered(scene)
        self._pixel = self._pixel_spread(scene, sensor)
        with _unwrapped(), common.traced_searches(scene), self._edges_on(scene, seed):
            grad = super().render_forward(scene, params, sensor, seed, spp)
            if self._kept is not None:
                # (after the replay's image: the film is reused, and Dr.Jit's
                # forward_to clears the graph that the replay's derivatives
                # go through)
                dr.eval(grad)
                kept, camera = self._handed()
                pairs = self._replay_edges(dr.ADMode.Forward, scene, *kept)
                grad = grad + self._replay_edges_forward(scene, sensor, pairs, camera)
            return grad

    @collection_paused()
    def render_backward(self, scene, params, grad_in, sensor=0, seed=0, spp=0):
        common.check(self, scene, sensor)
        self._check_differentiable(scene)
        self._warn_uncovered(scene)
        self._pixel = self._pixel_spread(scene, sensor)
        with _unwrapped(), common.traced_searches(scene), self._edges_on(scene, seed):
            super().render_backward(scene, params, grad_in, sensor, seed, spp)
            if self._kept is not None:
                self._replay_edges(dr.ADMode.Backward, scene, *self._handed()[0])

    @contextlib.contextmanager
    def _edges_on(self, scene, seed):
        """Within it (a gradient pass), the boundary terms of the moving
        lgsurfaces' silhouettes are added to the replay's own samples
        (:meth:`_replay_edges`): the camera rays are stratified over each
        pixel (:meth:`sample_rays`), the primal pass records the slots the
        terms need (:meth:`_slot_new`), the replay keeps them (``_kept``)
        for :meth:`_replay_edges`, which runs after Mitsuba's pass (its
        primal and replay kernel, fused). Nothing changes where ``boundary``
        is off or no lgsurface moves."""
        moving = self._moving(scene) if self.boundary else []
        self._edges = (moving, seed) if moving else None
        try:
            yield
        finally:
            self._edges = self._kept = self._camera = None

    def _handed(self):
        """What the replay kept for :meth:`_replay_edges` and the camera
        samples, taken off the integrator: left there, these wide arrays
        made a band's path loop (:meth:`_band_paths`) fail on a size
        mismatch (Dr.Jit counted them in the state of a loop that reads
        ``self``)."""
        out = (self._kept, self._camera)
        self._kept = self._camera = None
        return out

    def sample_rays(self, scene, sensor, sampler):
        """Mitsuba's camera rays; in a gradient pass with boundary terms
        (:meth:`_edges_on`) and ``stratified`` on, :meth:`_stratified_rays`'s."""
        if getattr(self, "_edges", None) is None:
            return super().sample_rays(scene, sensor, sampler)
        if self.stratified:
            out = self._stratified_rays(scene, sensor, sampler, self._edges[1])
        else:
            out = super().sample_rays(scene, sensor, sampler)
        self._camera = out                  # (the forward term's splat)
        return out

    @staticmethod
    def _check_differentiable(scene):
        """Raise :class:`~.checks.NotDifferentiableError` where an
        lgsurface's parameter with a gradient is one that f does not hold as
        a named constant (the shape's own check, made before any tracing)."""
        for shape in common.lg_shapes(scene):
            if shape.gradient_keys():
                shape._ad_forms()

    # ---- What a gradient pass leaves out ------------------------------------

    def uncovered(self, scene):
        """The terms of the derivative that a gradient pass on ``scene``
        leaves out, as messages naming the moving lgsurface (one with
        gradient-enabled parameters) and the term:

        - ``boundary`` is on, paths can see it after a bounce where that
          matters (``max_depth`` >= 3: a vertex after a bounce is lit; or
          ``max_depth`` 2 and some shape's BSDF has a delta or null
          component: a mirror, glass, a null surface), and the bounces that
          can see light (``max_depth`` - 1, unbounded at -1) outnumber
          ``bounce_edges``, the bounces whose silhouettes have their term
          (:meth:`_replay_edges`);
        - ``boundary`` is on and f changes sign on its box (:func:`_cut_by_box`):
          the edges where the box cuts the surface have no boundary term;
        - its BSDF has a delta reflection or transmission (a mirror, glass)
          and paths go on after it (``max_depth`` >= 2): the replay turns
          the reflected and refracted directions with the normals along the
          camera's first delta vertices (:meth:`_chain_rays`), but a delta
          vertex after a smooth bounce, or past :attr:`CHAIN`, keeps the
          direction to the next vertex fixed in the world; the silhouettes
          seen in it have no term (:meth:`_replay_edges`); and its own
          silhouette's band sees a curved mirror's image change fast. Said
          whether or not ``boundary`` is on.

        With ``boundary`` off, no boundary term at all is computed, as asked,
        and only the last item is said. (The light of an emitting lgsurface follows its
        shape: :meth:`_cone_sample_interior`, :meth:`_light_edges`.)"""
        lgs = common.lg_shapes(scene)
        moving = self._moving(scene)
        if not moving:
            return []
        depth = self.max_depth
        delta = [s for s in scene.shapes() if s.bsdf() is not None
                 and mi.has_flag(s.bsdf().flags(), mi.BSDFFlags.Delta)]
        left_out = "that part of the gradient is left out"
        out = []
        for k in moving:
            name = _lg_name(lgs, k)
            bsdf = lgs[k].bsdf()
            turning = mi.BSDFFlags.DeltaReflection | mi.BSDFFlags.DeltaTransmission
            if bsdf is not None and (int(bsdf.flags()) & int(turning)) and depth >= 2:
                out.append(f"lg_prb: the moving lgsurface {name} has a delta BSDF (a mirror, "
                           f"glass): the reflected and refracted directions turn with its "
                           f"normal along the first {min(self.CHAIN, depth - 1)} delta "
                           f"vertices from the camera, but not after a smooth bounce or past "
                           f"them, and the silhouettes seen in it or through it get no "
                           f"boundary term: {left_out}; its own silhouette's term is biased "
                           f"where what it shows changes fast across the band (a curved "
                           f"mirror's rim)")
            if not self.boundary:
                continue
            needed = depth - 1 if depth != 0xFFFFFFFF else None   # bounces that see light
            seen_after = depth >= 3 or (depth == 2 and delta)
            n = self._bounces()
            if seen_after and (needed is None or n < needed):
                why = (f"max_depth {'-1' if depth == 0xFFFFFFFF else depth}" if depth >= 3 else
                       f"max_depth 2 and the delta or null BSDF of "
                       f"{_shape_names(scene, delta)}") + f", bounce_edges {self.bounce_edges}"
                after = "after a bounce" if n == 0 else \
                    f"after more than {n} bounce{'s' if n > 1 else ''}"
                out.append(f"lg_prb: silhouettes of the moving lgsurface {name} seen {after} "
                           f"(in mirrors, through glass, in interreflections) get no "
                           f"boundary term ({why}): {left_out}")
            if _cut_by_box(lgs[k], self._cut):
                out.append(f"lg_prb: the moving lgsurface {name} reaches its bounding box (f "
                           f"changes sign on it: an open surface), and the edges where the "
                           f"box cuts it get no boundary term: {left_out}")
        return out

    def _warn_uncovered(self, scene):
        """Each of :meth:`uncovered`'s messages, once per scene, integrator
        and message (:func:`.checks.warn_once`)."""
        from .checks import warn_once
        for message in self.uncovered(scene):
            warn_once(scene, self, message, stacklevel=4)

    # ---- Visibility: the primary silhouettes of lgsurfaces ----------------

    @staticmethod
    def _pixel_spread(scene, sensor):
        """How neighbouring pixels' rays spread at the film's centre: (the
        angle between them, the distance between their origins: 0 and the
        pixel's size for a perspective and an orthographic camera). The
        shadow edges' band is ``band_width`` pixels of it at the occluder."""
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        with dr.suspend_grad():
            ray, _ = sensor.sample_ray_differential(0.0, 0.5, mi.Point2f(0.5), mi.Point2f(0.5))
            return (float(dr.norm(mi.Vector3f(ray.d_x) - mi.Vector3f(ray.d))[0]),
                    float(dr.norm(mi.Vector3f(ray.o_x) - mi.Vector3f(ray.o))[0]))

    def _band(self, distance, angle, footprint):
        """A band's width in world units: ``band_width`` pixels at
        ``distance`` from a camera whose neighbouring pixels' rays part by
        ``angle`` and start ``footprint`` apart (:meth:`_pixel_spread`)."""
        return self.band_width * (distance * angle + footprint)

    @staticmethod
    def _moving(scene):
        """The lgsurfaces whose parameters have gradients (by scene index)."""
        return [k for k, s in enumerate(common.lg_shapes(scene)) if s.gradient_keys()]

    def _stratified_rays(self, scene, sensor, sampler, seed):
        """The silhouette term's camera rays: ``sample_rays``'s, but with each
        pixel's spp film positions jittered over a k x k grid of its cells
        (k^2 >= spp; which cells, a random permutation per pixel and seed):
        each position is uniform over the pixel, as sample_rays's, and the
        fraction of a pixel's samples that fall in a silhouette's band varies
        far less from pixel to pixel. Films that sample a border take
        sample_rays's own positions."""
        film = sensor.film()
        spp = sampler.sample_count()
        if film.sample_border() or spp < 2:
            return RBIntegrator.sample_rays(self, scene, sensor, sampler)
        size = film.crop_size()
        k = 1
        while k * k < spp:
            k += 1
        index = dr.arange(mi.UInt32, dr.prod(size) * spp)
        pixel = index // dr.opaque(mi.UInt32, spp)
        j = index - pixel * dr.opaque(mi.UInt32, spp)
        seed = mi.UInt32(seed) ^ 0x5EED
        dr.make_opaque(seed)                # (a new seed compiles no new kernel)
        cell = mi.permute_kensler(j, k * k, mi.sample_tea_32(pixel, seed)[0])
        xi = sampler.next_2d()
        y = pixel // dr.opaque(mi.UInt32, size[0])
        x = pixel - y * dr.opaque(mi.UInt32, size[0])
        col = cell % k
        row = cell // k
        pos = mi.Vector2f(mi.Float(x) + (mi.Float(col) + xi.x) / k,
                          mi.Float(y) + (mi.Float(row) + xi.y) / k)
        aperture = sampler.next_2d() if sensor.needs_aperture_sample() else mi.Vector2f(0.0)
        time = sensor.shutter_open()
        if sensor.shutter_open_time() > 0:
            time += sampler.next_1d() * sensor.shutter_open_time()
        wavelength = sampler.next_1d() if mi.is_spectral else 0.0
        with dr.resume_grad():
            ray, weight = sensor.sample_ray_differential(
                time, wavelength, pos / mi.ScalarVector2f(size), aperture)
        # (a box filter splats at the pixel, as sample_rays does)
        splat = (mi.Vector2f(mi.Float(x), mi.Float(y)) if film.rfilter().is_box_filter()
                 else pos) + mi.Vector2f(film.crop_offset())
        return ray, weight, splat

    def _bounces(self):
        """How many bounces of each path get the term of the silhouettes
        they see (:meth:`_replay_edges`): the vertices i = 0 (the camera's
        hit) .. n - 1 whose sampled ray can bring light (i + 1 <
        ``max_depth``: emission after a delta BSDF), at most
        ``bounce_edges``."""
        depth = self.max_depth
        reach = self.bounce_edges if depth == 0xFFFFFFFF else max(0, depth - 1)
        return min(reach, self.bounce_edges)

    def _band_paths(self, scene, band, rays, seed, salt, **kwargs):
        """The primal radiance along each of ``rays`` on the ``band`` lanes (0
        elsewhere): the mean of ``band_paths`` path samples each (``sample``'s,
        with ``kwargs``), traced on those lanes alone, gathered into a
        wavefront of their own with an independent sampler seeded from ``seed``
        and ``salt`` (a silhouette's band holds a small part of the lanes;
        paths traced over all of them, masked, cost as much as the render
        itself)."""
        width = dr.width(band)
        out = [dr.zeros(mi.Spectrum, width) for _ in rays]
        # (evaluated together: each gather would otherwise launch what they
        # are computed from again)
        dr.eval(band, rays, [v for v in kwargs.values() if dr.is_array_v(v)])
        index = dr.compress(band)
        n = dr.width(index)
        if n == 0:
            return out
        if getattr(self, "_band_sampler", None) is None:
            self._band_sampler = mi.load_dict({"type": "independent"})
        sampler = self._band_sampler.clone()
        value = mi.UInt32(mi.sample_tea_32(mi.UInt32(seed), mi.UInt32(0xB0 + salt))[0])
        dr.make_opaque(value)               # (a new seed compiles no new kernel)
        m = self.band_paths
        # the rays' paths in one wavefront (one trace of the path loop):
        # lane j follows ray j // (n m) of its band sample
        sampler.seed(value, len(rays) * n * m)
        j = dr.arange(mi.UInt32, len(rays) * n * m)
        which = j // dr.opaque(mi.UInt32, n * m)    # (n varies: opaque, no new kernel)
        lane = dr.gather(mi.UInt32, index, (j - which * dr.opaque(mi.UInt32, n * m)) // m)
        kwargs = {k: dr.gather(type(v), v, lane) if dr.is_array_v(v) and dr.width(v) == width
                  and width > 1 else v for k, v in kwargs.items()}
        sub = dr.gather(mi.Ray3f, rays[0], lane)
        for q in range(1, len(rays)):
            sub = dr.select(which == q, dr.gather(mi.Ray3f, rays[q], lane), sub)
        L_sub = self.sample(dr.ADMode.Primal, scene, sampler, sub, None, None,
                            mi.Bool(True), record=False, **kwargs)[0]
        for q, L in enumerate(out):
            # (atomic adds: Dr.Jit's expanded reduction would write the
            # target's size, which varies with the band, into the kernel)
            dr.scatter_add(L, L_sub * (1.0 / m), lane, active=which == q,
                           mode=dr.ReduceMode.Local)
        return out

    # ---- The slots: what the boundary terms take from the primal pass -------

    def _slot_count(self, primal, camera, record):
        """How many slots (:meth:`_slot_new`) the primal pass records: the
        bounces that get the silhouettes' term (:meth:`_bounces`) in a
        gradient pass with boundary terms (:meth:`_edges_on`), for the
        camera's paths (``camera``) that are not a band's own (``record``);
        0 otherwise."""
        if not (primal and camera and record and self._edges is not None):
            return 0
        return self._bounces()

    @staticmethod
    def _slot_new(n):
        """n empty slots, one for the ray leaving each of the path's first n
        vertices: its origin and direction, its hit (which lgsurface, the
        distance; Mitsuba's preliminary intersection for all but the last:
        the next slot's vertex), the path's throughput after the vertex's
        BSDF sample, whether that sample was a delta one, whether the ray
        can bring light (``lit``), and the distance travelled from the
        camera to the hit."""
        def one(i):
            out = (mi.Point3f(0), mi.Vector3f(0), mi.UInt32(0), mi.Float(dr.inf),
                   mi.Spectrum(0), mi.Bool(False), mi.Bool(False), mi.Float(0))
            return out + ((dr.zeros(mi.PreliminaryIntersection3f),) if i < n - 1 else ())
        return tuple(one(i) for i in range(n))

    @staticmethod
    def _slot_add(slots, i, ray, hit, beta, delta, lit, dist):
        """``slots`` with slot ``i`` (a per-lane vertex index) set where it
        is that slot's."""
        def put(j, slot):
            here = i == j
            new = (ray.o, ray.d, hit.lg, hit.t, beta, delta, lit, dist)
            new = new + ((hit.pi,) if len(slot) > 8 else ())
            return tuple(dr.select(here, v, u) for v, u in zip(new, slot))
        return tuple(put(j, slot) for j, slot in enumerate(slots))

    def _replay_edges(self, mode, scene, camera_ray, seen, hit, slots, δL):
        """The boundary term of the silhouettes of moving lgsurfaces seen
        along the replay's own paths: from the camera (its rays stratified
        over each pixel: :meth:`sample_rays`) and after each of the first
        :meth:`_bounces` bounces (in mirrors, through glass, in
        interreflections), from the primal pass's slots (``state``).

        For a ray that hits a moving lgsurface, S (:meth:`LGSurface.silhouette`:
        min f / |grad f| over its chord through the solid, world units) is 0
        at the silhouette and below 0 inside; the radiance H L_s + (1 - H)
        L_b (H = [S < 0]) moves by -(L_s - L_b) delta(S) dS, delta relaxed
        over a band of ``band_width`` pixels (the pixels' angle at the
        distance travelled from the camera) inside the silhouette. L_s is the
        radiance along the ray, L_b along the ray continued past the
        surface's exit, each the mean of ``band_paths`` primal paths traced
        on the band's lanes alone (:meth:`_band_paths`) with the depth left.
        After a smooth BSDF they leave out the emission at their first hit
        (the edge of that light is the shadow-edge term's, whole); after a
        delta or null one they keep it. The term is the path's throughput
        times (L_s - L_b) w (-dS); S follows the surface's parameters and,
        after a bounce, the vertex's motion with its own surface (a vertex
        on a moving lgsurface also sees static lgsurfaces' silhouettes
        move). Under ``hide_emitters`` the camera's slot is the ray past the
        area emitters it hides (as the paths see it).

        ``seen`` and ``hit`` are the camera ray past the emitters it hides
        and its hit, ``slots`` the primal pass's (all evaluated with
        Mitsuba's pass: the replay schedules them). Each ray's lanes that
        hit a lgsurface concerned are gathered into a wavefront of their own
        before the silhouette's search. Backward: the term's adjoint (``δL``
        times it) is propagated here; forward: returns the (term, lanes)
        pairs for :meth:`_replay_edges_forward`."""
        moving, seed = self._edges
        lgs = common.lg_shapes(scene)
        seen = mi.Ray3f(seen)
        out = []
        with dr.suspend_grad():
            cam = mi.Vector3f(camera_ray.d)
            skipped = dr.dot(mi.Vector3f(seen.o) - mi.Vector3f(camera_ray.o), cam) \
                if self.hide_emitters else mi.Float(0)
            angle = dr.norm(mi.Vector3f(camera_ray.d_x) - cam)
            footprint = dr.norm(mi.Vector3f(camera_ray.o_x) - mi.Vector3f(camera_ray.o))
            # the rays: the camera's, then each slot's; with what each needs
            items = [dict(ray=seen, hit=hit, beta=None, delta=None,
                          lit=hit.is_valid(), dist=dr.detach(hit.t) + skipped, prev=None)]
            prev = (seen, hit)
            for i, slot in enumerate(slots):
                o, d, lg, t, beta, delta, lit, dist = slot[:8]
                ray = mi.Ray3f(o, d)
                h = Hit(pi=slot[8] if len(slot) > 8 else dr.zeros(mi.PreliminaryIntersection3f),
                        lg=lg, t=t)
                items.append(dict(ray=ray, hit=h, beta=beta, delta=delta, lit=lit,
                                  dist=dist, prev=prev,
                                  depth=i))
                prev = (ray, h)
            # which lanes of each ray concern which lgsurface
            for item in items:
                h, first = item["hit"], item["prev"] is None
                masks = {}
                on_moving = mi.Bool(False)
                if not first:
                    for k in moving:
                        on_moving |= item["prev"][1].lg == k + 1
                for k in range(len(lgs)):
                    if k in moving:
                        masks[k] = item["lit"] & (h.lg == k + 1)
                    elif not first:
                        # (after a delta BSDF the sampled direction turns with
                        # the moving vertex's normal, which S does not follow:
                        # left out, and said, by uncovered)
                        masks[k] = item["lit"] & (h.lg == k + 1) & on_moving & ~item["delta"]
                item["masks"] = masks
                any_ = mi.Bool(False)
                for m in masks.values():
                    any_ |= m
                item["any"] = any_
            dr.eval([item["any"] for item in items], skipped, angle, footprint)
            for n_item, item in enumerate(items):
                idx = dr.compress(item["any"])
                if dr.width(idx) == 0:
                    continue
                term = self._edge_term(scene, item, idx, moving, lgs, angle, footprint, seed,
                                       n_item, mode)
                if term is None:
                    continue
                if mode == dr.ADMode.Backward:
                    term, leaves = term
                    with dr.resume_grad():
                        dr.backward_from(dr.gather(mi.Spectrum, δL, idx) * term)
                        leaves.backpropagate()
                else:
                    out.append((term, idx))
        return out

    def _edge_term(self, scene, item, idx, moving, lgs, angle, footprint, seed, salt, mode):
        """One ray's term (:meth:`_replay_edges`) on its gathered lanes
        ``idx``: (term, leaves) backward, the term forward; None where it
        has no band lane."""
        g = lambda tp, v: dr.gather(tp, v, idx)
        ray = g(mi.Ray3f, item["ray"])
        t = g(mi.Float, item["hit"].t)
        first = item["prev"] is None
        if first:
            width = self._band(g(mi.Float, item["dist"]), g(mi.Float, angle),
                               g(mi.Float, footprint))
        else:
            width = self._band(g(mi.Float, item["dist"]), *self._pixel)
        leaves = common.WideLeaves(dr.width(idx)) if mode == dr.ADMode.Backward else None
        moving_ray = None
        if not first:
            p_ray, p_hit = item["prev"]
            p_hit = Hit(pi=g(mi.PreliminaryIntersection3f, p_hit.pi), lg=g(mi.UInt32, p_hit.lg),
                        t=g(mi.Float, p_hit.t))
            with dr.resume_grad():
                # the vertex as it moves with its own surface's parameters
                moving_ray = mi.Ray3f(ray)
                moving_ray.o = compute_interaction(scene, g(mi.Ray3f, p_ray), p_hit,
                                                   mi.RayFlags.Minimal).p
                if not dr.grad_enabled(moving_ray.o):
                    moving_ray = None
        S, w = mi.Float(0), mi.Float(0)
        t_exit, band = mi.Float(dr.inf), mi.Bool(False)
        for k, mask in item["masks"].items():
            if k not in moving and moving_ray is None:
                continue
            mine = g(mi.Bool, mask)
            with dr.resume_grad():
                S_k, w_k, te_k, band_k = lgs[k].silhouette(ray, t, width, mine, leaves,
                                                           moving_ray=moving_ray)
                S = dr.select(mine, S_k, S)
            w, t_exit, band = (dr.select(mine, v, u) for v, u in
                               ((w_k, w), (te_k, t_exit), (band_k, band)))
        behind = mi.Ray3f(ray)
        behind.o = mi.Point3f(ray(t_exit))
        if first:
            L_s, L_b = self._band_paths(scene, band, (ray, behind), seed, 0)
            beta = 1.0
        else:
            i = item["depth"]
            left = self.max_depth if self.max_depth == 0xFFFFFFFF else self.max_depth - (i + 1)
            L_s, L_b = self._band_paths(scene, band, (ray, behind), seed, 1 + i,
                                        max_depth=left, emission=g(mi.Bool, item["delta"]),
                                        camera=False)
            beta = g(mi.Spectrum, item["beta"])
        jump = dr.select(band, beta * (L_s - L_b) * w, 0.0)
        # (evaluated once: the term's gradients would each launch the paths again)
        dr.eval(jump)
        with dr.resume_grad():
            term = jump * dr.select(band, -S, 0.0)
        return (term, leaves) if mode == dr.ADMode.Backward else term

    def _replay_edges_forward(self, scene, sensor, pairs, camera):
        """The image of the forward derivative of :meth:`_replay_edges`'s
        terms (``pairs``), splatted at the gradient pass's camera samples
        (``camera``: :meth:`sample_rays`'s)."""
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        film = sensor.film()
        ray, weight, pos = camera
        out = dr.zeros(mi.Spectrum, dr.width(pos))
        with dr.resume_grad():
            for term, idx in pairs:
                dr.scatter_add(out, dr.detach(dr.forward_to(term)), idx)
        dr.eval(out, ray, weight, pos)
        film.prepare([])
        block = film.create_block()
        block.set_coalesce(block.coalesce() and dr.width(ray) >= 4 * dr.prod(film.crop_size()))
        self._splat(block, film, pos, out * weight, ray)
        film.put_block(block)
        return film.develop()

    @staticmethod
    def _splat(block, film, pos, value, ray):
        from mitsuba.python.ad.integrators.common import ADIntegrator
        ADIntegrator._splat_to_block(block, film, pos, value=value, weight=1.0, alpha=1.0,
                                     aovs=[], wavelengths=ray.wavelengths)

    @dr.syntax
    def sample(self, mode: dr.ADMode, scene: mi.Scene, sampler: mi.Sampler, ray: mi.Ray3f,
               δL, state_in, active: mi.Bool, max_depth=None, emission=True, camera=True,
               record=True, **kwargs):
        """One pass of path replay (``mode``: primal, backward or forward;
        see ``ADIntegrator.sample``). The primal pass returns the radiance
        and, as its state, (radiance, the path's record: :class:`PathRecord`,
        the camera ray and its first hit);
        the others replay the same path, subtracting each vertex's
        contribution from the primal radiance in ``state_in`` to know what
        the rest of the path brings, taking the record's hits and
        visibilities instead of tracing them again, and propagate ``δL``
        through each vertex's differentiable terms.

        In a gradient pass with boundary terms (:meth:`_edges_on`) the primal
        pass also records the slots of the paths' first bounces
        (:meth:`_slot_new`, handed over in the state), and the replay keeps
        them with its camera rays, their hits and ``δL`` (scheduled: they are
        evaluated in Mitsuba's kernel of the primal pass and the replay) for
        the silhouettes' term along its paths (:meth:`_replay_edges`, after
        the pass).

        :meth:`_band_paths` starts primal paths of its own: ``max_depth``
        (the depth left), ``emission`` (where False, the emission at the
        ray's first hit is left out: its edge is another term's), ``camera``
        False (after a bounce: ``hide_emitters`` does not apply) and
        ``record`` False (no slots)."""
        primal = mode == dr.ADMode.Primal
        n_slots = self._slot_count(primal, camera, record)
        camera_ray = ray
        max_depth = self.max_depth if max_depth is None else max_depth
        hide_emitters = self.hide_emitters and camera
        bsdf_ctx = mi.BSDFContext()

        # --------------------- Configure loop state ----------------------
        ray = mi.Ray3f(dr.detach(ray))
        depth = mi.UInt32(0)                                 # Vertex depth
        L = mi.Spectrum(0 if primal else state_in[0])        # Radiance (left to replay)
        # The primal pass's record of the path (PathRecord): the replay
        # takes its hits and shadow tests from it instead of tracing again
        rec = PathRecord(max_depth, len(common.lg_shapes(scene)))
        record = rec.new() if primal else rec.resumed(state_in[1])
        vertex = mi.UInt32(0)                                # Vertex index
        δL = mi.Spectrum(δL if δL is not None else 0)        # Adjoint radiance
        β = mi.Spectrum(1)                                   # Path throughput
        η = mi.Float(1)                                      # Relative IOR
        active = mi.Bool(active)
        valid_ray = mi.Bool(not hide_emitters and scene.environment() is not None)
        # The camera ray's hit (past the emitters it hides): the primal pass
        # hands it to the replay with the record
        if dr.hint(primal, mode="scalar"):
            hit = ray_intersect_preliminary(scene, ray, active)
            if dr.hint(hide_emitters, mode="scalar"):
                ray, hit = skip_area_emitters(scene, ray, hit, active)
        else:
            ray, hit = mi.Ray3f(state_in[2]), state_in[3]
        first = (mi.Ray3f(ray), hit)
        slots = self._slot_new(n_slots)
        skipped = mi.Float(0)
        if dr.hint(n_slots > 0 and hide_emitters, mode="scalar"):
            skipped = dr.dot(mi.Vector3f(ray.o) - mi.Vector3f(camera_ray.o),
                             mi.Vector3f(camera_ray.d))
        # The silhouettes' term along the replay's paths: what
        # _replay_edges takes after Mitsuba's pass, evaluated with it
        if dr.hint(not primal and self._edges is not None, mode="scalar"):
            self._kept = (camera_ray, mi.Ray3f(ray), hit, state_in[4], δL)
            dr.schedule(self._kept)

        # The shadow edges that lgsurfaces cast (_shadow_edge), replayed
        # (which move is known where gradients are not suspended)
        moving = None
        if dr.hint(not primal and self.boundary and self.shadow_edges
                   and bool(common.lg_shapes(scene)), mode="scalar"):
            with dr.resume_grad():
                moving = self._moving(scene)

        # The delta vertices from the camera (mirror, glass: _chain_rays)
        # that the replay turns with a moving lgsurface's normal: how many
        # it follows, and the lane's own (their hits, samples and count)
        chain = 0
        if dr.hint(not primal, mode="scalar"):
            with dr.resume_grad():
                chain = self._chain_length(scene)
        chain_hits, chain_u1, chain_u2, chain_n = self._chain_start(chain)

        travelled = mi.Float(0)                              # Path length to the vertex
        ray_prev = mi.Ray3f(ray)                             # The previous vertex:
        hit_prev = Hit(pi=dr.zeros(mi.PreliminaryIntersection3f), lg=mi.UInt32(0),
                       t=mi.Float(dr.inf))                  # its hit,
        si_prev = dr.zeros(mi.SurfaceInteraction3f)          # interaction,
        bsdf_pdf_prev = mi.Float(1)                          # BSDF pdf,
        bsdf_delta_prev = mi.Bool(True)                      # delta BSDF?

        while dr.hint(active, max_iterations=max_depth, label=f"lg_prb ({mode.name})"):
            active_next = mi.Bool(active)

            # The vertex, following the shapes' parameters (and the previous
            # vertex: the direction towards it moves with both)
            with dr.resume_grad(when=not primal):
                ray_in, ray_back = ray, ray_prev
                if dr.hint(chain > 0, mode="scalar"):
                    ray_in, ray_back = self._chain_rays(scene, chain, first[0], ray, ray_prev,
                                                        chain_hits, chain_u1, chain_u2,
                                                        chain_n, depth)
                si = compute_interaction(scene, ray_in, hit, active=active)
                # Does geometry move with the parameters? (Known while
                # tracing: the same for every vertex of every path.)
                moves = not primal and (dr.grad_enabled(si.p) or dr.grad_enabled(si.n))
                if dr.hint(moves, mode="scalar"):
                    # (a miss has no point: the direction to the environment
                    # stays, or turns with the camera's delta chain)
                    back = active & (depth > 0) & si.is_valid()
                    si_prev_d = compute_interaction(scene, ray_back, hit_prev,
                                                    mi.RayFlags.Minimal, back)
                    wi = si.to_local(dr.normalize(si_prev_d.p - si.p))
                    si.wi = dr.replace_grad(si.wi, dr.select(back, wi, si.wi))
            bsdf = si.bsdf(ray)

            # ---------------------- Direct emission ----------------------
            ds = mi.DirectionSample3f(scene, si=si, ref=si_prev)
            em_pdf = dr.select(bsdf_delta_prev, 0.0,
                               pdf_emitter_direction(scene, si_prev, ds, ~bsdf_delta_prev))
            mis = mis_weight(bsdf_pdf_prev, em_pdf)
            seen = (bsdf_pdf_prev > 0) & ((depth > 0) | emission)
            if dr.hint(hide_emitters, mode="scalar"):
                # the environment the camera ray escapes to is hidden too
                # (area emitters it hits were skipped: skip_area_emitters)
                seen &= (depth > 0) | si.is_valid()
            with dr.resume_grad(when=not primal):
                Le = β * mis * ds.emitter.eval(si, seen)

            active_next &= (depth + 1 < max_depth) & si.is_valid()

            # ---------------------- Emitter sampling ----------------------
            active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
            # (cone: the first hit of an lgsurface emitter's cone sample)
            ds, em_weight, tested, cone = sample_emitter_direction(scene, si, sampler.next_2d(),
                                                                   active_em, hit=True)
            active_em &= ds.pdf != 0
            sampled = mi.Bool(active_em)
            active_em, record = rec.visibility(scene, si.spawn_ray_to(ds.p), active_em, tested,
                                               primal, record, vertex)
            with dr.resume_grad(when=not primal):
                if dr.hint(not primal, mode="scalar"):
                    ds, em_weight = self._attach_emitter_sample(scene, si, ds, em_weight,
                                                                active_em, tested, moves, cone)
                wo = si.to_local(ds.d)
            # the edges of lgsurface emitters' light and of the shadows on
            # it, seen from this vertex (_light_edges; None: none moves)
            light_edges = None
            if dr.hint(not primal, mode="scalar"):
                light_edges = self._light_edges(scene, si, ds, em_weight, cone,
                                                sampled & tested, moves)

            # ------ Evaluate BSDF * cos(theta) and sample a direction ------
            sample_1, sample_2 = sampler.next_1d(), sampler.next_2d()
            # the shadowed samples near the edge of an lgsurface that moves,
            # or that the shadow ray's ends move against (None: none)
            edge = None
            if dr.hint(moving is not None, mode="scalar"):
                with dr.resume_grad():
                    edge = self._shadow_edge(scene, si, ds, sampled & ~active_em & ~tested,
                                             moving, travelled + dr.detach(hit.t))
            with dr.resume_grad(when=not primal):
                bsdf_val, bsdf_pdf = bsdf.eval_pdf(bsdf_ctx, si, wo,
                                                   sampled if edge is not None else active_em)
                mis_em = dr.select(ds.delta, 1.0, mis_weight(ds.pdf, bsdf_pdf))
                Lr_dir = dr.select(active_em, β * mis_em * bsdf_val * em_weight, 0.0)
                if dr.hint(edge is not None, mode="scalar"):
                    # what they would bring unoccluded (all of it: the
                    # boundary term has no BSDF-sampled counterpart here),
                    # times the band's weight, moving with the edge's
                    # distance S
                    w_e, S_e = edge
                    Lr_dir = Lr_dir + dr.detach(β * bsdf_val * em_weight * w_e) * \
                        (S_e - dr.detach(S_e))
                if dr.hint(light_edges is not None, mode="scalar"):
                    # the cone samples near the edge of an lgsurface emitter's
                    # light (its silhouette, or a moving lgsurface's in front
                    # of it): the jump across the edge, times the band's
                    # weight, moving with the edge (all of it, as above)
                    Lr_dir = Lr_dir + dr.detach(β * bsdf_val) * light_edges
            bs, bsdf_weight = bsdf.sample(bsdf_ctx, si, sample_1, sample_2, active_next)
            # a delta vertex of the camera's chain that the next one follows:
            # its sample's weight, attached (the Fresnel factor moves with
            # the normal; no area measure for the next vertex: it is not free)
            chain_delta, w_turn = None, None
            if dr.hint(chain > 0, mode="scalar"):
                turned = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta) & si.is_valid()
                chain_delta = active_next & turned & (depth == chain_n) & (depth < chain)
                with dr.resume_grad():
                    w_turn = bsdf.sample(bsdf_ctx, si, sample_1, sample_2, chain_delta)[1]
                chain_hits, chain_u1, chain_u2, chain_n = self._chain_push(
                    chain_hits, chain_u1, chain_u2, chain_n, depth, hit, sample_1, sample_2,
                    active & turned)

            # ---------------------- BSDF sampling ----------------------
            L = (L + Le + Lr_dir) if primal else (L - Le - Lr_dir)
            ray_next = si.spawn_ray(si.to_world(bs.wo))
            η *= bs.eta
            β *= bsdf_weight
            valid_ray |= active & si.is_valid() & ~mi.has_flag(bs.sampled_type,
                                                                mi.BSDFFlags.Null)

            # -------------------- Stopping criterion ---------------------
            depth[si.is_valid()] += 1
            β_max = dr.max(mi.unpolarized_spectrum(β))
            rr_prob = dr.minimum(β_max * η * η, 0.95)
            rr_active = depth >= self.rr_depth
            rr_continue = sampler.next_1d() < rr_prob
            β[rr_active] *= dr.rcp(rr_prob)
            active_next &= (~rr_active | rr_continue) & (β_max != 0)

            vertex += 1
            if dr.hint(primal, mode="scalar"):
                hit_next = ray_intersect_preliminary(scene, ray_next, active_next)
                record = rec.add(record, vertex, hit_next)
                if dr.hint(n_slots > 0, mode="scalar"):
                    # (a smooth vertex's ray brings reflected light only: a
                    # vertex after it must have a bounce left)
                    delta_s = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
                    slots = self._slot_add(
                        slots, vertex - 1, ray_next, hit_next, β, delta_s,
                        active_next & (delta_s | (vertex + 1 < max_depth)),
                        travelled + hit.t + hit_next.t + skipped)
            else:
                hit_next, record = rec.replayed_hit(scene, ray_next, active_next, record,
                                                    vertex)

            # -------------- Differential phase: this vertex --------------
            if dr.hint(not primal, mode="scalar"):
                δL = self._propagate(mode, scene, bsdf, bsdf_ctx, si, ray_next, hit_next, L,
                                     Le, Lr_dir, δL, active_next, moves, chain_delta, w_turn)

            # ------------------------ The next vertex ------------------------
            travelled += dr.select(si.is_valid(), dr.detach(hit.t), 0.0)
            ray_prev, hit_prev = ray, hit
            si_prev = dr.detach(si, True)
            bsdf_pdf_prev = bs.pdf
            bsdf_delta_prev = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
            ray, hit = ray_next, hit_next
            active = active_next

        return (L if primal else δL, valid_ray, [],
                (L, rec.handed_over(record), *first, slots))

    # ---- The camera's delta chain: mirrors and glass that move -------------

    def _chain_length(self, scene):
        """How many delta vertices from the camera the replay turns
        (:attr:`CHAIN`, at most ``max_depth`` - 1: the vertices that have a
        next one; called with gradients on): 0 where no moving lgsurface
        has a delta reflection or transmission, or paths end at their first
        vertex. (A glass slab's light crosses two faces and, a few per cent
        of it, reflects inside: its derivative needs about 4.)"""
        if self.max_depth < 2:
            return 0
        turning = int(mi.BSDFFlags.DeltaReflection | mi.BSDFFlags.DeltaTransmission)
        lgs = common.lg_shapes(scene)
        for k in self._moving(scene):
            bsdf = lgs[k].bsdf()
            if bsdf is not None and int(bsdf.flags()) & turning:
                return min(self.CHAIN, self.max_depth - 1)
        return 0

    @staticmethod
    def _chain_start(chain):
        """The empty chain (:meth:`_chain_push`): ``chain`` hits, first and
        second samples, and the lanes' count."""
        hits = [Hit(pi=dr.zeros(mi.PreliminaryIntersection3f), lg=mi.UInt32(0),
                    t=mi.Float(dr.inf)) for _ in range(chain)]
        return hits, [mi.Float(0) for _ in hits], [mi.Point2f(0) for _ in hits], mi.UInt32(0)

    @staticmethod
    def _chain_push(hits, u1, u2, n, depth, hit, sample_1, sample_2, delta):
        """The chain after vertex ``depth`` (its ``hit``, its BSDF samples):
        one longer on the ``delta`` lanes whose vertices so far were all
        delta ones (``depth == n``), unchanged elsewhere."""
        grow = delta & (depth == n)
        at = [grow & (depth == j) for j in range(len(hits))]
        hits = [dr.select(a, hit, h) for a, h in zip(at, hits)]
        u1 = [dr.select(a, sample_1, u) for a, u in zip(at, u1)]
        u2 = [dr.select(a, sample_2, u) for a, u in zip(at, u2)]
        return hits, u1, u2, dr.select(grow, n + 1, n)

    @staticmethod
    def _chain_rays(scene, chain, camera_ray, ray, ray_prev, hits, u1, u2, n, k):
        """``ray`` and ``ray_prev`` (detached: the rays into vertices ``k``
        and ``k`` - 1) with the derivatives of the rays that the camera's
        delta chain sends there, where the vertices before them all had a
        delta BSDF sample (the ray into vertex m: ``m <= n``, the lane's
        chain, and ``m <= chain``): the camera ray turned at each by its
        BSDF's sample (the same samples), each vertex following its
        surface's parameters and the turned ray before it (the
        implicit-function theorem along an attached ray; Mitsuba's shapes
        follow it too). A mirror's or glass's reflected and refracted
        directions then turn with its normal, and what is seen in it moves
        with them. Elsewhere the rays as they are (a vertex moving with its
        own surface alone). One walk along the chain gives both."""
        ctx = mi.BSDFContext()
        r = mi.Ray3f(camera_ray)
        r_back = mi.Ray3f(camera_ray)
        for j in range(chain):
            r_back = dr.select(k == j + 1, r, r_back)     # the ray into vertex j
            go = (j < k) & (j < n)
            si = compute_interaction(scene, r, hits[j], active=go)
            bs = si.bsdf(r).sample(ctx, si, u1[j], u2[j], go)[0]
            r = dr.select(go, si.spawn_ray(si.to_world(bs.wo)), r)
        r_back = dr.select(k == chain + 1, r, r_back)

        def attached(detached, chained, m):
            ok = (m <= n) & (m <= chain)
            out = mi.Ray3f(detached)
            out.o = dr.replace_grad(detached.o, dr.select(ok, chained.o, detached.o))
            out.d = dr.replace_grad(detached.d, dr.select(ok, chained.d, detached.d))
            return out
        return attached(ray, r, k), attached(ray_prev, r_back, k - 1)

    def _shadow_edge(self, scene, si, ds, shadowed, moving, distance):
        """The shadow edges' boundary term at a vertex, for its emitter samples
        that an lgsurface occludes: (w, S), or None where no edge moves. The
        occluders are the lgsurfaces in ``moving`` (scene indices) and, where
        the shadow ray's ends move (a moving shading point or light sample),
        every lgsurface: a static occluder's edge moves against a moving
        shading point too. Along the shadow ray, the occluder's S (its
        silhouette's distance proxy, :meth:`LGSurface.silhouette`, attached to
        its parameters) and the band's weight w
        (:func:`.lgsurface.edge_weight`: what the sample would bring unoccluded
        varies smoothly across the band; 0 where the ray is deep in the solid,
        or something else occludes it behind the occluder's exit). The band is
        :attr:`SHADOW_BAND` times ``band_width`` pixels at the shading point,
        ``distance`` along the path from the camera, carried along the shadow
        rays to the occluder (which narrow towards a light sample at finite
        distance): the shadow's edge is then about as wide on the image as
        twice a silhouette's band. The sample's visibility V = [S > 0] moves by
        delta(S) dS, relaxed to w dS; S follows the occluder's parameters and
        the motion of the shading point and the light sample."""
        from .lgsurface import edge_weight
        lgs = common.lg_shapes(scene)
        moving_ray = si.spawn_ray_to(ds.p)          # (attached where its ends move)
        if dr.grad_enabled(moving_ray.o) or dr.grad_enabled(moving_ray.d):
            moving = range(len(lgs))
        if not moving:
            return None
        ray = dr.detach(moving_ray)
        hit = ray_intersect_preliminary(scene, ray, shadowed)
        # (the shadow ray's t runs from 0 at the vertex to 1 at the light sample)
        width = self.SHADOW_BAND * self._band(distance, *self._pixel) * \
            dr.maximum(1.0 - hit.t, 0.0)
        w, S = mi.Float(0), mi.Float(0)
        for k in moving:
            mine = shadowed & (hit.lg == k + 1)
            with dr.resume_grad():
                S_k, w_k, t_exit, band = lgs[k].silhouette(ray, hit.t, width, mine,
                                                           moving_ray=moving_ray,
                                                           weight=edge_weight)
                S = dr.select(mine, S_k, S)
            band &= t_exit < ray.maxt
            behind = mi.Ray3f(ray)
            behind.o = mi.Point3f(ray(t_exit))
            behind.maxt = ray.maxt - t_exit
            band &= ~ray_test(scene, behind, band)
            w = dr.select(mine & band, w_k, w)
        return w, S

    def _attach_emitter_sample(self, scene, si, ds, em_weight, active, tested, moves,
                               cone=None):
        """The emitter sample's direction and weight as functions of the
        vertex (its motion, where geometry ``moves``) and of the emitter's
        parameters: the sampled emitter point stays fixed, the direction
        towards it and the solid-angle density move with si.p (Mitsuba's
        prb does the same). On a native shape's textured (spatially varying)
        area emitter, the sample is intersected again from just before it,
        as prb does: its point and uv follow that shape's motion, and the
        emission its texture lookup. On an lgsurface's emitter (``tested``
        lanes, ``cone``: the cone ray's hit) the same holds for the motion
        of si.p, and the sample also follows the emitting shape's own
        parameters (:meth:`_cone_sample_interior`)."""
        is_infinite = mi.has_flag(ds.emitter.flags(), mi.EmitterFlags.Infinite)
        is_surface = mi.has_flag(ds.emitter.flags(), mi.EmitterFlags.Surface)
        textured_em = _textured_native_emitters(scene)
        if textured_em:
            textured = active & ~tested & is_surface & \
                mi.has_flag(ds.emitter.flags(), mi.EmitterFlags.SpatiallyVarying)
            ray_em = si.spawn_ray_to(ds.p)
            # from just before the sample (its visibility is known)
            ray_em.o = dr.fma(ray_em.d, ray_em.maxt, ray_em.o)
            ray_em.maxt = dr.largest(mi.Float)
            si_em = scene.ray_intersect(ray_em, textured)      # native shapes: the emitter's
            ds = dr.replace_grad(ds, dr.select(textured, mi.DirectionSample3f(scene, si_em, si),
                                               dr.zeros(mi.DirectionSample3f)))
        if moves or textured_em:
            ds.d = dr.replace_grad(ds.d, dr.select(is_infinite, ds.d,
                                                   dr.normalize(ds.p - si.p)))
        value = scene.eval_emitter_direction(si, ds, active)
        inv_pdf = dr.select(ds.pdf != 0, dr.rcp(ds.pdf), 0.0)
        em_weight = dr.replace_grad(em_weight, value * dr.detach(inv_pdf))
        if cone is not None:
            em_weight = em_weight + self._cone_sample_interior(scene, si, ds, active & tested,
                                                               cone)
        if not moves:
            return ds, em_weight
        J = solid_angle_to_area_jacobian(si.p, dr.detach(ds.p), dr.detach(ds.n),
                                         active & is_surface)
        return ds, em_weight * dr.relative_grad(J)

    def _cone_sample_interior(self, scene, si, ds, lanes, cone):
        """The interior term of the cone samples (``lanes``) that hit a
        moving emitting lgsurface: with the shading point and the sampled
        direction fixed (the cone and its density do not depend on the
        shape's parameters: its bounding sphere is a constant), the hit
        moves along the ray by the implicit-function theorem
        (:func:`.common.compute_interaction` under ``dr.resume_grad``) and
        the emission is evaluated there again (a textured radiance follows
        the hit's uv). Returns a term of value 0 whose derivative is that
        (the emission's own parameters keep theirs from the sample's
        value: the two evaluations' difference cancels them); 0 where no
        emitting lgsurface moves. The motion of si.p is the area form's
        (:meth:`_attach_emitter_sample`), and the light's edge has its own
        term (:meth:`_light_edges`)."""
        lgs = common.lg_shapes(scene)
        with dr.resume_grad():
            movers = [k for k in self._moving(scene) if lgs[k].emitter() is not None]
        if not movers:
            return 0.0
        on = mi.Bool(False)
        for k in movers:
            on |= lanes & (cone.lg == k + 1) & (ds.emitter == mi.EmitterPtr(lgs[k].emitter()))
        ray = dr.detach(si).spawn_ray(dr.detach(ds.d))     # the cone ray, as sampled
        hit = Hit(pi=dr.zeros(mi.PreliminaryIntersection3f), lg=dr.select(on, cone.lg, 0),
                  t=dr.select(on, cone.t, dr.inf))
        inv_pdf = dr.detach(dr.select(ds.pdf > 0, dr.rcp(ds.pdf), 0.0))
        with dr.resume_grad():
            si_e = compute_interaction(scene, ray, hit, active=on)
            value = ds.emitter.eval(si_e, on) - ds.emitter.eval(dr.detach(si_e), on)
            return dr.select(on, value * inv_pdf, 0.0)

    def _light_edges(self, scene, si, ds, em_weight, cone, lanes, moves):
        """The boundary terms of the cone samples (``lanes``, of
        lgsurfaces' emitters: :func:`.common.sample_emitter_direction`;
        ``cone``: each one's first hit) at a vertex, for the light's edges
        seen from it: a term of value 0 whose derivative is theirs, in the
        units of ``em_weight`` (the caller multiplies by beta times the
        BSDF value), or None where there is none to compute (``boundary``
        off, or nothing moves).

        - The emitter's own silhouette (where its shape moves, or the
          shading point ``moves``): a sample that hits it inside the band
          of its silhouette (S < 0, :meth:`LGSurface.silhouette`, band
          ``light_band`` times the cone's radius at the hit) brings f_hit
          (``em_weight``) where the ray continued past the emitter's exit
          brings f_behind (the emitter hit again: a non-convex emitter;
          usually 0). With H = [S < 0], f = H f_hit + (1 - H) f_behind
          moves by -(f_hit - f_behind) delta(S) dS, relaxed to the band's
          weight w (:func:`.lgsurface.edge_weight`: the emission varies
          smoothly across the band). The shape's parameters move the edge at the fixed
          sampled direction (S of the fixed ray); the shading point's
          motion is the area form's (:meth:`_attach_emitter_sample`: the
          sample point fixed), in which only the hidden part f_behind has
          an edge (the visible part's horizon has none: its cosine
          vanishes there), S then following the ray from si.p to the point
          behind. So w (-f_hit dS_1 + f_behind dS_2), S_1 of the fixed ray
          and S_2 of the ray from the moving si.p to the fixed point
          behind (both attached to the shape's parameters).
        - The shadows that an lgsurface casts on the samples
          (``shadow_edges`` on; a moving one, or any where the shading
          point ``moves``): a sample whose ray it stops inside the band of
          its silhouette, and whose ray continued past its exit reaches
          the sampled emitter first, brings f_behind there: visibility
          [S > 0] moves by delta(S) dS, the term is w f_behind dS_2.

        The BSDF-sampled rays that hit the emitter have no edge term of
        their own: this one is the whole integrand's, not its MIS share."""
        if not self.boundary:
            return None
        from .lgsurface import edge_weight
        lgs = common.lg_shapes(scene)
        with dr.resume_grad():
            moving = self._moving(scene)
        emitting = [k for k, shape in enumerate(lgs) if shape.emitter() is not None]
        own = [k for k in emitting if moves or k in moving]
        # (a static lgsurface's shadow on the light moves where the vertex does)
        occluders = ([] if not self.shadow_edges else
                     list(range(len(lgs))) if moves else moving)
        if not emitting or not (own or occluders):
            return None
        em_lg = mi.UInt32(0)                    # the sampled emitter's lgsurface (k + 1)
        for k in emitting:
            em_lg = dr.select(ds.emitter == mi.EmitterPtr(lgs[k].emitter()), k + 1, em_lg)
        ray = dr.detach(si).spawn_ray(dr.detach(ds.d))     # the cone ray, as sampled
        # the band: light_band times the radius of the sampled emitter's
        # cone at the hit's distance (the cone holds its bounding sphere)
        tan_cone = mi.Float(0.0)
        for k in emitting:
            _, cos_max, _ = common._cone(lgs[k], dr.detach(si.p))
            tan_k = dr.safe_sqrt(1.0 - cos_max * cos_max) / dr.maximum(cos_max, 1e-6)
            tan_cone = dr.select(em_lg == k + 1, tan_k, tan_cone)
        width = self.light_band * dr.detach(cone.t * dr.norm(ray.d) * tan_cone)
        f_hit = dr.detach(em_weight)
        inv_pdf = dr.detach(dr.select(ds.pdf > 0, dr.rcp(ds.pdf), 0.0))
        term = mi.Spectrum(0.0)
        for k in sorted(set(own) | set(occluders)):
            is_own = em_lg == k + 1
            mine = lanes & (cone.lg == k + 1) & \
                ((is_own & (k in own)) | (~is_own & (k in occluders)))
            with dr.resume_grad():
                S_1, w, t_exit, band = lgs[k].silhouette(ray, cone.t, width, mine,
                                                         weight=edge_weight)
            behind = mi.Ray3f(ray)
            behind.o = mi.Point3f(ray(t_exit))
            behind.maxt = dr.largest(mi.Float)
            hit_b = ray_intersect_preliminary(scene, behind, band)
            lit = band & (hit_b.lg == em_lg) & (em_lg != 0)
            si_b = compute_interaction(scene, behind, hit_b, active=lit)
            f_behind = dr.detach(dr.select(lit, ds.emitter.eval(si_b, lit) * inv_pdf, 0.0))
            S_2 = S_1
            if moves:
                with dr.resume_grad():
                    moving_ray = si.spawn_ray(dr.detach(ds.d))
                    moving_ray.d = dr.normalize(dr.detach(si_b.p) - moving_ray.o)
                    S_2 = lgs[k].silhouette(ray, cone.t, width, lit, moving_ray=moving_ray)[0]
            with dr.resume_grad():
                w = dr.detach(w)
                dS_1 = dr.select(band & is_own, S_1 - dr.detach(S_1), 0.0)
                dS_2 = dr.select(lit, S_2 - dr.detach(S_2), 0.0)
                term = term + w * (f_behind * dS_2 - dr.select(is_own, f_hit, 0.0) * dS_1)
        return term

    def _propagate(self, mode, scene, bsdf, bsdf_ctx, si, ray_next, hit_next, L, Le, Lr_dir,
                   δL, active_next, moves, chain_delta=None, w_turn=None):
        """The differentiable radiance leaving this vertex: its emission,
        its emitter sample, and the rest of the path (L, already replayed
        out of the primal value) through the BSDF value and, where geometry
        ``moves``, the area measure of the next vertex; then δL times it,
        backward or forward. Returns δL (forward: with this vertex's
        derivative added). Where nothing moves, the direction to the next
        vertex and its measure carry no derivative: the next vertex is not
        computed. On the ``chain_delta`` lanes (a delta vertex of the
        camera's chain, :meth:`_chain_rays`) the rest of the path goes
        through the sample's attached weight ``w_turn`` instead, and the
        next vertex has no measure of its own (it follows this one)."""
        if moves:
            si_next = compute_interaction(scene, ray_next, hit_next, mi.RayFlags.Minimal,
                                          active_next)
        with dr.resume_grad():
            if moves:
                next_ok = active_next & si_next.is_valid()
                J = dr.relative_grad(solid_angle_to_area_jacobian(si.p, si_next.p, si_next.n,
                                                                  next_ok))
                wo_world = dr.replace_grad(ray_next.d, dr.select(
                    next_ok, dr.normalize(si_next.p - si.p), ray_next.d))
            else:
                J, wo_world = 1.0, ray_next.d
            bsdf_val = bsdf.eval(bsdf_ctx, si, si.to_local(wo_world), active_next)
            factor = dr.relative_grad(bsdf_val) * J
            if chain_delta is not None:
                factor = dr.select(chain_delta, dr.relative_grad(w_turn), factor)
            Lr_ind = L * factor
            Lo = Le + Lr_dir + Lr_ind
            if mode == dr.ADMode.Backward:
                dr.backward_from(δL * Lo)
                return δL
            return δL + dr.forward_to(Lo)

    def aov_names(self):
        return []

    def to_string(self):
        return common.describe_depths(self)
