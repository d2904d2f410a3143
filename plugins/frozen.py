"""Frozen renders: the lg integrators' primal render replayed without tracing.

An lg integrator's ``sample()`` is Python: tracing it (the lgsurfaces'
searches, Mitsuba's BSDFs and emitters) costs tens of milliseconds on the
host at every render, whatever the image size. :func:`render` runs the
render as a Dr.Jit frozen function (``dr.freeze``): after a render has
been traced once, later renders of the same scene launch the recorded
kernels with new inputs (the seed, the scene's current parameters).

What a recording may depend on, and how a change is noticed:

- Dr.Jit arrays: Mitsuba's objects are traversed by Dr.Jit itself; the
  arrays that lgshape's objects hold (the lgsurfaces' grids, tables and
  opaque constants, the emitters' data) are gathered by :func:`state` and
  passed as inputs, so their current values are read at every replay.
- Python values that tracing reads (a grid's resolution, an expression's
  structure, a flag, a depth): :func:`state` also returns a key of every
  scalar held by lgshape's objects and of the identity of each expression
  node (nodes are interned: one object per structure). A new key is a new
  recording.
- Caches filled while tracing (opaque constants made on first use): a
  recording must not create arrays that outlive it. So a key is first
  rendered traced, not frozen; it is replayed only once a traced render
  left the key unchanged (the caches were warm).

A render that starts while another one runs on the same thread (a
nested call) is traced: a frozen function must not record or replay
inside another one's recording. Renders that record derivatives are
never frozen: only a render with gradients suspended (``mi.render``'s
primal render) is; gradient passes (Mitsuba's default ones render again
with gradients on) are traced. An integrator whose
``FREEZE_AUTO_OPAQUE`` is False records with every input opaque (Dr.Jit's
``auto_opaque=False``; a recording may then compile kernels the traced
render did not: cornell.xml's under lg_path did). Set
``LGSHAPE_NO_FREEZE=1`` to trace every render.
"""
from __future__ import annotations

import collections
import contextlib
import os
import threading
import weakref

import drjit as dr
import mitsuba as mi
import numpy as np

from lgshape.trace import call_frozen, collection_paused

from .common import check, traced_searches

#: Recordings kept per integrator (keys beyond it are traced each time).
LIMIT = 8
#: The integrator's attribute that holds its recordings (:class:`_Recordings`).
_SLOT = "_frozen_render"
#: Per thread: how many renders of this module are running (a render that
#: starts inside another one is traced, never frozen or recorded).
_ACTIVE = threading.local()


@contextlib.contextmanager
def _entered():
    """Counts a render as running on this thread; yields how many were
    running before it."""
    depth = getattr(_ACTIVE, "depth", 0)
    _ACTIVE.depth = depth + 1
    try:
        yield depth
    finally:
        _ACTIVE.depth = depth


def enabled() -> bool:
    return os.environ.get("LGSHAPE_NO_FREEZE", "") in ("", "0")


def _is_ours(obj) -> bool:
    return (type(obj).__module__ or "").startswith("lgshape")


def state(scene, integrator):
    """(arrays, key): the Dr.Jit arrays held by lgshape's objects in the
    scene (lgsurfaces, emitters, the integrator), and a hashable key of the
    Python values they hold (see the module's docstring)."""
    from lgshape.expr.node import Expr

    arrays, key, seen = [], [], set()

    def walk(obj):
        if dr.is_array_v(obj):
            arrays.append(obj)
            key.append((type(obj).__name__, dr.width(obj) == 1))
            return
        if obj is None or isinstance(obj, (bool, int, float, str, bytes, type)):
            key.append(obj)
            return
        if id(obj) in seen:
            key.append(("seen", id(obj)))
            return
        seen.add(id(obj))
        if isinstance(obj, Expr):
            key.append(("expr", id(obj)))      # interned: identity is structure
        elif isinstance(obj, np.ndarray):
            key.append(("np", obj.shape, obj.dtype.str,
                        obj.tobytes() if obj.size <= 64 else id(obj)))
        elif isinstance(obj, dict):
            key.append(("dict", len(obj)))
            for k, v in obj.items():
                walk(k)
                walk(v)
        elif isinstance(obj, (list, tuple, set, frozenset)):
            key.append((type(obj).__name__, len(obj)))
            for v in (sorted(obj, key=repr) if isinstance(obj, (set, frozenset)) else obj):
                walk(v)
        elif _is_ours(obj):
            key.append(type(obj).__qualname__)
            fields = getattr(obj, "__dict__", None)
            if fields is None:
                fields = {s: getattr(obj, s) for s in getattr(type(obj), "__slots__", ())
                          if hasattr(obj, s)}
            for k, v in fields.items():
                if k != _SLOT:
                    key.append(k)
                    walk(v)
        else:
            # Mitsuba's objects (Dr.Jit traverses them), functions, modules.
            key.append(("other", type(obj).__qualname__))

    for obj in (integrator, *scene.shapes(), *scene.emitters()):
        if _is_ours(obj):
            walk(obj)
    return arrays, tuple(key)


class _Recordings:
    """One integrator's frozen render and the keys known to be warm."""

    def __init__(self, base, integrator):
        self.warm = collections.OrderedDict()
        owner = weakref.ref(integrator)     # (no cycle through the integrator)

        def run(scene, sensor, seed, spp, key, arrays):
            return _render_and_reseed(base, owner(), scene, sensor, seed, spp)

        self.fn = dr.freeze(run, limit=LIMIT, warn_after=2 ** 30,
                            auto_opaque=getattr(integrator, "FREEZE_AUTO_OPAQUE", True))


def _recording_gradients() -> bool:
    """Is Dr.Jit recording derivatives here (gradients not suspended)?
    ``mi.render`` runs the primal render with them suspended; Mitsuba's
    default gradient passes render again with them on, and that render
    must be attached to the scene's parameters, so it is traced."""
    probe = mi.Float(0)
    dr.enable_grad(probe)
    return dr.grad_enabled(probe)


def _sampler(scene, sensor):
    return (scene.sensors()[sensor] if isinstance(sensor, int) else sensor).sampler()


def _render_and_reseed(base, integrator, scene, sensor, seed, spp):
    """The render, then the sensor's sampler seeded afresh on one lane: its
    state after the render depends on the whole path loop, and a frozen
    function evaluates the state it leaves behind (a second, large kernel).
    (``mi.render`` does the same after the render.)"""
    image = base(integrator, scene, sensor, seed, spp, True, True)
    _sampler(scene, sensor).seed(0, 1)
    return image


def render(integrator, base, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
    """``base(integrator, scene, sensor, seed, spp, develop, evaluate)``
    (Mitsuba's render of the integrator's class), frozen where it can be
    (see the module's docstring; a frozen render's image is evaluated
    whatever ``evaluate`` says), with the lgsurfaces' searches traced into
    the render's kernels in either case."""
    with traced_searches(scene), _entered() as outer:
        # The sampler's state on entry, the same evaluated array in every
        # render (a frozen function would otherwise evaluate whatever the
        # last render left, in a kernel the first render did not have).
        sampler = _sampler(scene, sensor)
        sampler.seed(0, 1)
        sampler.schedule_state()
        dr.eval()
        if outer or not (enabled() and develop and dr.is_jit_v(mi.Float)):
            return base(integrator, scene, sensor, seed, spp, develop, evaluate)
        if _recording_gradients():
            return base(integrator, scene, sensor, seed, spp, develop, evaluate)
        arrays, key = state(scene, integrator)
        # Every input an evaluated array, in the traced renders as in the
        # recording (a literal or unevaluated input would be compiled into
        # the one and evaluated before the other: two kernels).
        dr.make_opaque(*arrays)
        rec = integrator.__dict__.get(_SLOT)
        if rec is None:
            rec = integrator.__dict__[_SLOT] = _Recordings(base, integrator)
        seed = seed if isinstance(seed, mi.UInt32) else dr.opaque(mi.UInt32, int(seed))
        if key in rec.warm:
            rec.warm.move_to_end(key)
            return call_frozen(rec.fn, scene, sensor, seed, spp, hash(key), arrays)
        # Traced: fills the caches; the key is warm if it did not change.
        image = _render_and_reseed(base, integrator, scene, sensor, seed, spp)
        dr.eval(image)
        if state(scene, integrator)[1] == key:
            rec.warm[key] = True
            while len(rec.warm) > LIMIT:
                rec.warm.popitem(last=False)
        return image


@collection_paused()
def sampling_render(integrator, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
    """The ``render`` of the lg integrators built on ``mi.SamplingIntegrator``
    (``mi.render`` calls the Python method): :func:`.common.check`, then
    Mitsuba's own, frozen where it can be (:func:`render`)."""
    check(integrator, scene, sensor)
    return render(integrator, mi.SamplingIntegrator.render, scene, sensor, seed, spp,
                  develop, evaluate)
