"""Shared code of the lg integrators: ray queries that see both Mitsuba's
native geometry and every ``lgsurface`` of a scene.

Native shapes go through ``scene.ray_intersect`` / ``scene.ray_test``
(Embree or OptiX); each ``lgsurface`` goes through its own guaranteed ray
search (:meth:`LGSurface.intersect`), limited to the part of the ray in
front of the nearest hit found so far. The result is one complete
:class:`mitsuba.SurfaceInteraction3f` whichever kind of shape was hit, so
the integrators use Mitsuba's BSDFs and emitters unchanged.
"""
from __future__ import annotations

import contextlib
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi


# ---------------------------------------------------------------------------
#  Finding the implicit surfaces of a scene
# ---------------------------------------------------------------------------

def lg_shapes(scene: mi.Scene) -> list:
    """The ``lgsurface`` shapes of ``scene``, in scene order."""
    return [s for s in scene.shapes() if getattr(s, "IS_LGSURFACE", False)]


def refresh_infinite_emitters(scene: mi.Scene) -> None:
    """Give every infinite emitter (constant, envmap, directional, ...) the
    scene's current bounds again. Mitsuba 3.9.1's ``Scene.parameters_changed``
    calls the environment emitter's ``set_scene`` *before* it recomputes the
    bounds (so it keeps those of the previous update) and never calls that of
    a directional emitter; after ``params.update()`` moved or resized a shape
    (an lgsurface or a native one), their bounding spheres would be stale and
    the render would differ from a fresh load. ``set_scene`` only derives the
    bounding sphere from ``scene.bbox()``: calling it again with unchanged
    bounds changes nothing. The lg integrators call this before rendering."""
    for emitter in scene.emitters():
        if mi.has_flag(emitter.flags(), mi.EmitterFlags.Infinite):
            emitter.set_scene(scene)


def read_depths(integrator, props: mi.Properties) -> None:
    """``max_depth`` (-1: no limit, kept as 2^32 - 1) and ``rr_depth`` of a
    path tracer, as Mitsuba's ``path`` reads them, checked; set on
    ``integrator`` (its ``PLUGIN`` names it in the errors)."""
    name = integrator.PLUGIN
    max_depth = props.get("max_depth", -1)
    if max_depth < -1:
        raise ValueError(f"{name}: 'max_depth' must be -1 (no limit) or >= 0")
    integrator.max_depth = 0xFFFFFFFF if max_depth == -1 else int(max_depth)
    integrator.rr_depth = int(props.get("rr_depth", 5))
    if integrator.rr_depth <= 0:
        raise ValueError(f"{name}: 'rr_depth' must be > 0")


def describe_depths(integrator) -> str:
    """``Class[max_depth = ..., rr_depth = ...]`` (``to_string``)."""
    depth = -1 if integrator.max_depth == 0xFFFFFFFF else integrator.max_depth
    return (f"{type(integrator).__name__}[\n  max_depth = {depth},\n"
            f"  rr_depth = {integrator.rr_depth}\n]")


def check(integrator, scene, sensor=0) -> None:
    """What the lg integrators do before a render: the checks of
    :func:`.checks.check_render` (media the integrator ignores, gradients it
    cannot carry; for a direct ``integrator.render(scene)``, as ``mi.render``
    checks before), then :func:`refresh_infinite_emitters`."""
    from .checks import check_render
    check_render(scene, integrator, sensor, stacklevel=4)
    refresh_infinite_emitters(scene)


# ---------------------------------------------------------------------------
#  Combined ray queries
# ---------------------------------------------------------------------------

@dataclass
class Hit:
    """The nearest hit along a ray before its surface interaction is
    computed (what a differentiable integrator keeps from one bounce to the
    next): ``pi``, Mitsuba's preliminary intersection with the native shapes
    (invalid where an lgsurface is nearer), ``lg`` (0: a native shape or
    none, k + 1: the scene's k-th lgsurface, :func:`lg_shapes`) and ``t``,
    the nearest hit's distance (inf: none). Dr.Jit loops carry it as state."""
    pi: object
    lg: object
    t: object

    def is_valid(self):
        return dr.isfinite(self.t)

    def emitter(self, scene):
        """The area emitter of the shape hit (None lanes: none)."""
        out = dr.select(self.lg == 0, self.pi.shape.emitter(), dr.zeros(mi.EmitterPtr))
        for k, shape in enumerate(lg_shapes(scene)):
            if shape.emitter() is not None:
                out = dr.select(self.lg == k + 1, mi.EmitterPtr(shape.emitter()), out)
        return out


@contextlib.contextmanager
def traced_searches(scene):
    """Within it, the lgsurfaces' standalone searches are traced into the
    caller's kernel rather than run frozen (:meth:`lgshape.trace.Surface.trace`):
    for a pass of several searches over few lanes, each frozen call would
    first evaluate its inputs in a kernel of its own."""
    surfaces = [shape.surface for shape in lg_shapes(scene)]
    saved = [s.freeze for s in surfaces]
    for s in surfaces:
        s.freeze = False
    try:
        yield
    finally:
        for s, f in zip(surfaces, saved):
            s.freeze = f


class WideLeaves:
    """Wide stand-ins for width-1 differentiable values (a surface's
    parameters) in a backward pass over many lanes. Dr.Jit reduces the
    gradient of each width-1 value that wide lanes depend on in its own
    kernel, which computes the lanes' adjoints again; through these leaves
    (:meth:`wide`: a detached copy of the value per lane, with a gradient)
    the adjoints of all of them are evaluated in one kernel, then summed
    and handed on to the values (:meth:`backpropagate`)."""

    def __init__(self, width):
        self.width = width
        self.pairs = []

    def wide(self, value):
        """A wide leaf standing for ``value`` (``value`` itself where it has
        no gradient)."""
        if not dr.grad_enabled(value):
            return value
        leaf = dr.detach(value) + dr.zeros(type(dr.detach(value)), self.width)
        dr.enable_grad(leaf)
        self.pairs.append((leaf, value))
        return leaf

    def backpropagate(self):
        """After a backward pass into the leaves: their gradients, summed
        over the lanes, into the values they stand for (and on to what those
        depend on)."""
        if not self.pairs:
            return
        grads = [dr.grad(leaf) for leaf, _ in self.pairs]
        dr.eval(grads)
        total = sum(dr.detach(dr.sum(g)) * value for g, (_, value) in zip(grads, self.pairs))
        dr.backward_from(total)
        self.pairs = []


def ray_intersect_preliminary(scene: mi.Scene, ray: mi.Ray3f, active=True,
                              search=True) -> Hit:
    """The nearest hit along ``ray`` among native shapes and lgsurfaces
    (:class:`Hit`). Each lgsurface is searched in front of the nearest hit
    found so far; a ray spawned from an lgsurface does not hit it again at
    its origin (see :data:`lgsurface.SELF_HIT_EPSILON`). ``search``: the
    lanes where the lgsurfaces are searched; elsewhere the nearest native
    hit is the answer (for a pass that knows no lgsurface is nearer, as
    lg_prb's replay)."""
    active = mi.Bool(active)
    pi = scene.ray_intersect_preliminary(ray, coherent=False, active=active)
    t_near = dr.select(pi.is_valid(), pi.t, ray.maxt)
    nearest = mi.UInt32(0)
    ray_k = mi.Ray3f(ray)
    searched = active & search
    for k, shape in enumerate(lg_shapes(scene)):
        ray_k.maxt = t_near
        t, hit = shape.intersect(ray_k, searched)
        closer = searched & hit & (t < t_near)
        t_near = dr.select(closer, t, t_near)
        nearest = dr.select(closer, k + 1, nearest)
    pi = dr.select(nearest == 0, pi, dr.zeros(mi.PreliminaryIntersection3f))
    t = dr.select((nearest != 0) | pi.is_valid(), t_near, dr.inf)
    return Hit(pi=pi, lg=nearest, t=t)


def compute_interaction(scene: mi.Scene, ray: mi.Ray3f, hit: Hit, flags=mi.RayFlags.All,
                        active=True) -> mi.SurfaceInteraction3f:
    """The complete surface interaction at ``hit`` along ``ray``
    (``si.is_valid()`` is false where there is none). Under
    :func:`drjit.resume_grad` it follows the shapes' parameters that have
    gradients: native shapes as Mitsuba's do, lgsurfaces through the
    implicit-function theorem (:meth:`LGSurface.compute_surface_interaction`)."""
    active = mi.Bool(active)
    si = hit.pi.compute_surface_interaction(ray, flags, active & (hit.lg == 0))
    for k, shape in enumerate(lg_shapes(scene)):
        mine = active & (hit.lg == k + 1)
        pi = dr.zeros(mi.PreliminaryIntersection3f)
        pi.t = dr.select(mine, hit.t, dr.inf)
        si = dr.select(mine, shape.compute_surface_interaction(ray, pi, flags, mine), si)
    return si


def ray_intersect(scene: mi.Scene, ray: mi.Ray3f, active=True) -> mi.SurfaceInteraction3f:
    """The nearest hit along ``ray`` among native shapes and lgsurfaces, as a
    complete surface interaction (:func:`ray_intersect_preliminary`, then
    :func:`compute_interaction`)."""
    return compute_interaction(scene, ray, ray_intersect_preliminary(scene, ray, active),
                               active=active)


def ray_test(scene: mi.Scene, ray: mi.Ray3f, active=True) -> mi.Bool:
    """Is anything (native or implicit) hit in (0, ray.maxt)? For shadow rays
    such as ``si.spawn_ray_to(p)``."""
    active = mi.Bool(active)
    occluded = scene.ray_test(ray, active)
    for shape in lg_shapes(scene):
        occluded |= shape.occluded(ray, active & ~occluded)
    return occluded


def skip_area_emitters(scene: mi.Scene, ray: mi.Ray3f, hit: Hit, active=True):
    """Continue ``ray`` through directly visible area emitters (for
    ``hide_emitters``): (ray, hit), the ray last spawned (its direction is
    ``ray``'s) and its first hit that is not an emitter, or a miss."""
    skip = mi.Bool(active) & hit.is_valid() & (hit.emitter(scene) != None)  # noqa: E711

    def body(ray, hit, skip):
        si = compute_interaction(scene, ray, hit, mi.RayFlags.Minimal, skip)
        ray = dr.select(skip, si.spawn_ray(ray.d), ray)
        hit = dr.select(skip, ray_intersect_preliminary(scene, ray, skip), hit)
        return ray, hit, skip & hit.is_valid() & (hit.emitter(scene) != None)  # noqa: E711

    ray, hit, _ = dr.while_loop((mi.Ray3f(ray), hit, skip), lambda ray, hit, skip: skip, body,
                                label="lg: skip area emitters")
    return ray, hit


# ---------------------------------------------------------------------------
#  Emitter sampling: area emitters on lgsurfaces
# ---------------------------------------------------------------------------
#
# Mitsuba's area emitter samples its shape through the shape's C++
# sample_position / pdf_position, which never reach an lgsurface (a Python
# mesh subclass: no trampoline), so the lg integrators sample the emitters of
# lgsurfaces themselves: the emitter is chosen as Mitsuba chooses (its
# sampling weight), then a direction uniformly in the cone of the surface's
# bounding sphere (of its occupied pruning cells, in world space) seen from
# the shading point, traced: where its first hit is the surface, that hit is
# the sample, with the cone's density, exact; elsewhere the sample is
# occluded (the trace is its shadow test). The same density is the pdf of a
# BSDF-sampled direction that hits the surface, for MIS.

def _lg_emitters(scene):
    """[(k, shape, index in scene.emitters())] for the lgsurfaces with an
    area emitter."""
    emitters = list(scene.emitters())
    out = []
    for k, shape in enumerate(lg_shapes(scene)):
        em = shape.emitter()
        if em is None:
            continue
        index = next(i for i, e in enumerate(emitters) if e.ptr == em.ptr)
        out.append((k, shape, index))
    return out


def _cone(shape, p):
    """(axis, cos of the cone's half angle, inside) of the shape's bounding
    sphere seen from the points p (inside: p within the sphere, the whole
    sphere of directions)."""
    c, r = shape.bounding_sphere()
    to_c = mi.Vector3f(c) - mi.Vector3f(p)
    d2 = dr.squared_norm(to_c)
    inside = d2 <= r * r
    cos_max = dr.safe_sqrt(1.0 - r * r / dr.select(inside, 1.0, d2))
    return dr.normalize(to_c), dr.select(inside, -1.0, cos_max), inside


def _cone_pdf(cos_max):
    return dr.rcp(2.0 * dr.pi * (1.0 - cos_max))


def _first_non_null(scene, ray, active):
    """(ray, hit): the first hit along ``ray`` on a surface whose BSDF is not
    ``null`` (null surfaces, such as media boundaries, let the direction
    pass as BSDF sampling does), with the ray last spawned."""
    hit = ray_intersect_preliminary(scene, ray, active)

    def null_hit(ray, hit, go):
        si = compute_interaction(scene, ray, hit, active=go)
        return go & hit.is_valid() & \
            mi.has_flag(si.bsdf(ray).flags(), mi.BSDFFlags.Null) & (hit.emitter(scene) == None)  # noqa: E711

    go = null_hit(ray, hit, mi.Bool(active))

    def body(ray, hit, go):
        si = compute_interaction(scene, ray, hit, mi.RayFlags.Minimal, go)
        ray = dr.select(go, si.spawn_ray(ray.d), ray)
        hit = dr.select(go, ray_intersect_preliminary(scene, ray, go), hit)
        return ray, hit, null_hit(ray, hit, go)

    ray, hit, _ = dr.while_loop((mi.Ray3f(ray), hit, go), lambda ray, hit, go: go, body,
                                label="lg: through null surfaces")
    return ray, hit


def sample_emitter_direction(scene, si, sample, active=True, through_null=False, hit=False):
    """Emitter sampling that includes the area emitters of lgsurfaces:
    (ds, weight, tested). As ``scene.sample_emitter_direction(si, sample,
    False, active)`` for the scene's other emitters; for an lgsurface's,
    the traced cone sample above: ``tested`` marks those lanes, whose
    visibility is part of the sample (weight 0 where occluded), so that no
    shadow ray is needed there. ``hit``: also return the cone ray's first
    hit (a :class:`Hit`, along ``si.spawn_ray(ds.d)``; lg 0 and t inf
    outside ``tested``), as a fourth value: lg_prb attaches the sample to
    the emitter's parameters from it, and finds the edges it lies near.

    ``through_null``: whether the cone sample passes through ``null``
    surfaces. False for the integrators whose shadow rays stop at any
    surface (lg_path, lg_prb, lg_direct: Mitsuba's ``path`` tests
    visibility with ``ray_test``, and a BSDF sample through a null surface
    is a delta sample there, counted without MIS); True for lg_volpath,
    whose shadow paths cross null surfaces (its caller then computes their
    transmittance, as ``volpath``)."""
    active = mi.Bool(active)
    ds, weight = scene.sample_emitter_direction(si, sample, False, active)
    tested = mi.Bool(False)
    cone = Hit(pi=dr.zeros(mi.PreliminaryIntersection3f), lg=mi.UInt32(0), t=mi.Float(dr.inf))
    ours = _lg_emitters(scene)
    if not ours:
        return (ds, weight, tested, cone) if hit else (ds, weight, tested)
    index, sel_weight, reused = scene.sample_emitter(sample.x, active)
    for k, shape, em_index in ours:
        mine = active & (index == em_index)
        axis, cos_max, _ = _cone(shape, si.p)
        local = mi.warp.square_to_uniform_cone(mi.Point2f(reused, sample.y), cos_max)
        d = mi.Frame3f(axis).to_world(local)
        if through_null:
            ray, first = _first_non_null(scene, si.spawn_ray(d), mine)
        else:
            ray = si.spawn_ray(d)
            first = ray_intersect_preliminary(scene, ray, mine)
        on = mine & (first.lg == k + 1)
        si_e = compute_interaction(scene, ray, first, active=on)
        em = shape.emitter()
        ds_k = dr.zeros(mi.DirectionSample3f)
        ds_k.p, ds_k.n, ds_k.uv = si_e.p, si_e.n, si_e.uv
        ds_k.time = si.time
        ds_k.d = d
        ds_k.dist = dr.norm(si_e.p - si.p)
        ds_k.pdf = _cone_pdf(cos_max) * scene.pdf_emitter(em_index, mine)
        ds_k.delta = mi.Bool(False)
        ds_k.emitter = mi.EmitterPtr(em)
        value = em.eval(si_e, on)
        w = dr.select(on, value * sel_weight * dr.rcp(_cone_pdf(cos_max)), 0.0)
        ds = dr.select(mine, ds_k, ds)
        weight = dr.select(mine, w, weight)
        tested |= mine
        cone = dr.select(mine, first, cone)
    return (ds, weight, tested, cone) if hit else (ds, weight, tested)


def pdf_emitter_direction(scene, ref, ds, active=True):
    """``scene.pdf_emitter_direction(ref, ds, active)``, with the density of
    :func:`sample_emitter_direction` where ``ds.emitter`` is an lgsurface's."""
    active = mi.Bool(active)
    pdf = scene.pdf_emitter_direction(ref, ds, active)
    for k, shape, em_index in _lg_emitters(scene):
        mine = active & (ds.emitter == mi.EmitterPtr(shape.emitter()))
        _, cos_max, _ = _cone(shape, ref.p)
        pdf = dr.select(mine, _cone_pdf(cos_max) * scene.pdf_emitter(em_index, mine), pdf)
    return pdf


# ---------------------------------------------------------------------------
#  Sampling helpers
# ---------------------------------------------------------------------------

def mis_weight(pdf_a, pdf_b):
    """Power heuristic (β = 2) weight of technique a; 0 where undefined."""
    a2, b2 = pdf_a * pdf_a, pdf_b * pdf_b
    w = a2 / (a2 + b2)
    return dr.detach(dr.select(dr.isfinite(w), w, 0.0))
