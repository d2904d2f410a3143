"""Python's garbage collector and the kernels the lg integrators trace.

Dr.Jit 1.5 names a virtual call's callable by its code but keys it by its
code and by whether the call has one instance or several. A vcall over
Mitsuba's shapes has one instance per shape alive in the process, so a
scene's shapes freed between two vcalls of one kernel make that kernel
define one function twice, and the process aborts: in the suite, at random,
when a collection freed an earlier test's scene while a new scene's first
render was traced. The lg integrators' renders and gradient passes run with
the collector paused (``lgshape.trace.collection_paused``).

Oracles, each in a child process (an abort ends the process):
- the abort itself: two ``compute_surface_interaction`` calls on the same
  rays, with an earlier scene's sphere freed between them, make LLVM refuse
  the kernel (the message CI's aborts left);
- the exit status of a render (or gradient pass) during which a collection
  would free an earlier scene's shapes: a ``gc.callbacks`` hook frees that
  scene at the first collection after the integrator traced its first
  ``compute_interaction``, with the collector's thresholds at 1. Without the
  pause the lg_path case aborts with the same message and the same function
  (``func_c604049e...``, the name CI's abort gave; the other cases happened
  not to trace a second identical call after the free); with it, the
  collection comes after the render. The render equals the next render at
  the same seed, bit for bit (box filter).
"""
from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

from conftest import VARIANT


CHILD = """
import gc, sys
import lgshape
import drjit as dr, mitsuba as mi, numpy as np
mi.set_variant(VARIANT); lgshape.register_plugins()
import lgshape.plugins.common as common

def scene(radius):
    return mi.load_dict({"type": "scene", "integrator": {"type": INTEGRATOR, "max_depth": 3},
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at([0, -5, 1], [0, 0, 0], [0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": 8, "height": 8, "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": 2}},
        "sky": {"type": "constant", "radiance": 0.3},
        "light": {"type": "point", "position": [2.0, -3.0, 3.0], "intensity": 10.0},
        "s": {"type": "lgsurface", "expr": "x^2 + y^2 + z^2 - radius^2", "radius": radius,
              "bbox_min": [-1.1] * 3, "bbox_max": [1.1] * 3}})

held = [scene(1.0)]          # the earlier scene, alive until the hook drops it
current = scene(0.9)
params = mi.traverse(current)
if GRADIENT:
    dr.enable_grad(params["s.radius"])
    params.update()

traced = []
inner = common.compute_interaction
def counted(*args, **kwargs):
    out = inner(*args, **kwargs)
    traced.append(1)
    return out
for module in list(sys.modules.values()):
    if getattr(module, "compute_interaction", None) is inner:
        module.compute_interaction = counted

def hook(phase, info):
    if phase == "start" and traced and held:
        held.clear()
        print("freed after", len(traced), "traced calls")

def run():
    image = mi.render(current, params, seed=1)
    if GRADIENT:
        dr.backward(dr.mean(image, axis=None))
        return np.array(dr.grad(params["s.radius"]))
    return np.array(image)

gc.callbacks.append(hook)
gc.set_threshold(1, 1, 1)
first = run()
gc.set_threshold(700, 10, 10)
assert not held, "the hook never ran"
if GRADIENT:
    dr.set_grad(params["s.radius"], 0)
again = run()
print("equal" if np.array_equal(first, again) and np.any(first != 0) else "differ")
"""


def child(code, **names):
    """Run ``code`` in a fresh interpreter with ``names`` defined first."""
    prelude = "".join(f"{k} = {v!r}\n" for k, v in names.items())
    return subprocess.run([sys.executable, "-c", prelude + code], capture_output=True,
                          text=True, timeout=300)


def test00_a_shape_freed_between_two_vcalls_aborts_the_kernel():
    # Oracle: the child's exit status and LLVM's message. This is the cause
    # the pause works around; if a later Dr.Jit keys its callables by code
    # alone, the child succeeds and this test says so.
    code = textwrap.dedent(f"""
        import gc, drjit as dr, mitsuba as mi
        mi.set_variant({VARIANT!r})
        ball = lambda: mi.load_dict({{"type": "scene", "s": {{"type": "sphere"}}}})
        earlier, current = ball(), ball()
        x = dr.linspace(mi.Float, -2, 2, 64)
        ray = mi.Ray3f(mi.Point3f(x, 0, -5), mi.Vector3f(0, 0, 1))
        pi = current.ray_intersect_preliminary(ray)
        first = pi.compute_surface_interaction(ray).t        # two shapes alive
        del earlier
        gc.collect()
        second = pi.compute_surface_interaction(ray).t       # one shape alive
        dr.eval(first + second)
        print("evaluated")
    """)
    run = child(code)
    assert run.returncode != 0 and "evaluated" not in run.stdout, (
        "Dr.Jit no longer defines the callable twice: collection_paused may be unneeded")
    assert "invalid redefinition of function" in run.stderr


@pytest.mark.parametrize("integrator, gradient", [
    ("lg_path", False), ("lg_volpath", False), ("lg_prb", False), ("lg_prb", True)])
def test01_a_collection_cannot_free_shapes_while_a_render_is_traced(integrator, gradient):
    # Oracles: the child's exit status (no abort), the hook's report that it
    # freed the earlier scene (after the render), and the next render (or
    # gradient) at the same seed, bit for bit.
    run = child(CHILD, VARIANT=VARIANT, INTEGRATOR=integrator, GRADIENT=gradient)
    assert run.returncode == 0, run.stderr[-3000:]
    assert "freed after" in run.stdout
    assert run.stdout.strip().endswith("equal"), run.stdout
