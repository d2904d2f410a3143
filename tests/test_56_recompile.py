"""No kernel is compiled after the first render of a scene: a new seed
reuses the kernels of the first render, under every lg integrator, for
primal renders and for lg_prb's gradient passes.

Oracle: Dr.Jit's kernel history (``JitFlag.KernelHistory``). The hashes of
the JIT kernels each render launches are compared with those of the first
render (not the ``cache_hit`` flags: a kernel cached on disk by an earlier
process would hide a recompile). A kernel whose code depends on how many
times the scene was rendered (a frozen function's recording against its
replays, a value cached during the first trace) shows as a hash that the
first render did not launch.
"""
from __future__ import annotations

import drjit as dr
import lgshape
import mitsuba as mi
import pytest

from conftest import VARIANT
from test_57_frozen import scene as lit_torus


@pytest.fixture(scope="module", autouse=True)
def variant():
    mi.set_variant(VARIANT)
    lgshape.register_plugins()
    yield


def cornell(integrator):
    """scenes/cornell.xml, small, and the integrator to render it with."""
    return mi.load_file("scenes/cornell.xml", resx=12, resy=12, spp=2), mi.load_dict(integrator)


def scene(integrator):
    """test_57's lit torus (an lgsurface torus lit by an emitting lgsurface
    ball and a sky, on a native floor: camera hits, emitter hits and
    emitter samples on lgsurfaces), and its integrator."""
    s = lit_torus(integrator)
    return s, s.integrator()


def kernels(fn):
    """The hashes of the JIT kernels that fn() launches."""
    dr.kernel_history()                      # drop what came before
    dr.eval(fn())
    dr.sync_thread()
    return [k["hash"] for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]


def new_kernels(render, count=4):
    """Hashes launched by renders 2..count (new seeds) that render 1 did not launch."""
    flag = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        first = set(kernels(lambda: render(0)))
        later = [kernels(lambda: render(seed)) for seed in range(1, count)]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, flag)
    assert first
    return [[h for h in hashes if h not in first] for hashes in later]


INTEGRATORS = [
    {"type": "lg_path", "max_depth": 4},
    {"type": "lg_direct"},
    {"type": "lg_aov", "aovs": "dd:depth,nn:sh_normal"},
    {"type": "lg_volpath", "max_depth": 4},
    {"type": "lg_prb", "max_depth": 4},
]


CASES = [(scene, i) for i in INTEGRATORS] + [(cornell, INTEGRATORS[0])]


@pytest.mark.parametrize("make, integrator", CASES,
                         ids=[f"{m.__name__}-{i['type']}" for m, i in CASES])
def test01_renders_compile_only_once(make, integrator):
    s, integ = make(integrator)
    assert new_kernels(lambda seed: mi.render(s, integrator=integ, seed=seed)) == [[]] * 3


@pytest.mark.parametrize("key, mode", [("white.reflectance.value", "backward"),
                                       ("tangle.to_world", "forward")])
def test02_gradient_passes_compile_only_once(key, mode):
    s, integ = cornell({"type": "lg_prb", "max_depth": 3})
    params = mi.traverse(s)
    assert key in params, sorted(params.keys())

    def render(seed):
        p = mi.traverse(s)
        if key.endswith("to_world"):
            # A translation's derivative, as an optimisation of the shape's position would take.
            x = mi.Float(0.0)
            dr.enable_grad(x)
            p[key] = mi.Transform4f().translate(mi.Point3f(x, 0, 0)) @ mi.Transform4f(p[key])
            p.update()
            leaf = x
        else:
            dr.enable_grad(p[key])
            p.update()
            leaf = p[key]
        if mode == "forward":
            dr.forward(leaf, dr.ADFlag.ClearEdges)
            img = mi.render(s, p, integrator=integ, seed=seed)
            return dr.forward_to(img)
        img = mi.render(s, p, integrator=integ, seed=seed)
        dr.backward(dr.mean(img, axis=None))
        return dr.grad(leaf)

    assert new_kernels(render) == [[]] * 3
