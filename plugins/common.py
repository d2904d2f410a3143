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


def render(integrator, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
    """The lg integrators' ``render`` (``mi.render`` calls the Python method):
    the checks of :func:`.checks.check_render` (media the integrator
    ignores, gradients on lgsurface parameters; for a direct
    ``integrator.render(scene)``, as ``mi.render`` checks before), then
    :func:`refresh_infinite_emitters`, then Mitsuba's own."""
    from .checks import check_render
    check_render(scene, integrator, sensor, stacklevel=3)
    refresh_infinite_emitters(scene)
    return mi.SamplingIntegrator.render(integrator, scene, sensor, seed, spp, develop, evaluate)


# ---------------------------------------------------------------------------
#  Combined ray queries
# ---------------------------------------------------------------------------

def ray_intersect(scene: mi.Scene, ray: mi.Ray3f, active=True) -> mi.SurfaceInteraction3f:
    """The nearest hit along ``ray`` among native shapes and lgsurfaces, as a
    complete surface interaction (``si.is_valid()`` is false where the ray
    escapes). A ray spawned from an lgsurface does not hit it again at its
    origin (see :data:`lgsurface.SELF_HIT_EPSILON`)."""
    active = mi.Bool(active)
    si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.All, coherent=False, active=active)
    lgs = lg_shapes(scene)
    if not lgs:
        return si

    # ---- Nearest implicit hit in front of the native one ----
    t_near = dr.select(si.is_valid(), si.t, ray.maxt)
    nearest = mi.UInt32(0)                   # 0: native or none, k + 1: lgs[k]
    ray_k = mi.Ray3f(ray)
    for k, shape in enumerate(lgs):
        ray_k.maxt = t_near
        t, hit = shape.intersect(ray_k, active)
        closer = active & hit & (t < t_near)
        t_near = dr.select(closer, t, t_near)
        nearest = dr.select(closer, k + 1, nearest)

    # ---- Surface interaction at the implicit hit ----
    pi = dr.zeros(mi.PreliminaryIntersection3f)
    pi.t = t_near
    for k, shape in enumerate(lgs):
        mine = nearest == k + 1
        si = dr.select(mine, shape.compute_surface_interaction(ray, pi, mi.RayFlags.All, mine), si)
    return si


def ray_test(scene: mi.Scene, ray: mi.Ray3f, active=True) -> mi.Bool:
    """Is anything (native or implicit) hit in (0, ray.maxt)? For shadow rays
    such as ``si.spawn_ray_to(p)``."""
    active = mi.Bool(active)
    occluded = scene.ray_test(ray, active)
    for shape in lg_shapes(scene):
        occluded |= shape.occluded(ray, active & ~occluded)
    return occluded


def skip_area_emitters(scene: mi.Scene, ray: mi.Ray3f, si, active=True):
    """Continue ``ray`` through directly visible area emitters (for
    ``hide_emitters``): the first hit that is not an emitter, or a miss."""
    skip = mi.Bool(active) & si.is_valid() & (si.shape.emitter() != None)  # noqa: E711

    def body(si, skip):
        nxt = ray_intersect(scene, si.spawn_ray(ray.d), skip)
        si = dr.select(skip, nxt, si)
        return si, skip & si.is_valid() & (si.shape.emitter() != None)  # noqa: E711

    si, _ = dr.while_loop((si, skip), lambda si, skip: skip, body,
                          label="lg: skip area emitters")
    return si


# ---------------------------------------------------------------------------
#  Sampling helpers
# ---------------------------------------------------------------------------

def mis_weight(pdf_a, pdf_b):
    """Power heuristic (β = 2) weight of technique a; 0 where undefined."""
    a2, b2 = pdf_a * pdf_a, pdf_b * pdf_b
    w = a2 / (a2 + b2)
    return dr.detach(dr.select(dr.isfinite(w), w, 0.0))
