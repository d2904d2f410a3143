"""Named constants (scene parameters): their value never changes the
expression's structure, so a new value reuses the compiled kernels.

Oracle: the same expression with the values written as plain constants,
evaluated in float64 (the function must be the same)."""
from __future__ import annotations

import numpy as np
import pytest

import lgshape
from lgshape.arraymath import NUMPY
from lgshape.expr import evaluate
from lgshape.expr.node import named
from lgshape.tables import _structure
from conftest import VARIANT

TEXT = "x^2 + y^2 + z^2 - radius^2 + k*x*y - k"


@pytest.mark.parametrize("values", [(0.0, 0.0), (1.0, 1.0), (0.5, 0.25), (1.0, 0.5)])
def test_structure_does_not_depend_on_values(values):
    r, k = values
    f = lgshape.parse(TEXT, constants={"radius": r, "k": k})
    ref = lgshape.parse(TEXT, constants={"radius": 0.75, "k": 0.125})
    assert _structure(f)[0] == _structure(ref)[0]
    # plain constants fold 0 and 1 and merge equal values: another structure
    plain = lgshape.parse(TEXT.replace("radius", repr(r)).replace("k", repr(k)))
    p = np.random.default_rng(0).uniform(-2, 2, (200, 3))
    env = {v: p[:, i] for i, v in enumerate("xyz")}
    assert np.array_equal(np.broadcast_to(evaluate(f, env, NUMPY), 200),
                          np.broadcast_to(evaluate(plain, env, NUMPY), 200))


def test_named_constant_checks():
    with pytest.raises(ValueError, match="not finite"):
        named("r", float("inf"))
    assert repr(lgshape.parse("x - r", constants={"r": 2.0})) == "x - 2"
    assert repr(lgshape.parse("x^n", constants={"n": 3})) == "x^3"   # an exponent is structure


def test_kernels_equal_for_new_values():
    """Dr.Jit kernel hashes of the search are equal for radius 1 and 0.5
    (and k 0 and 1, values that plain constants would fold away)."""
    import drjit as dr
    hashes = []
    for r, k in ((1.0, 0.0), (0.5, 1.0)):
        f = lgshape.parse(TEXT, constants={"radius": r, "k": k})
        s = lgshape.Surface(f, bbox=((-2,) * 3, (2,) * 3), depth=4)
        o = np.tile([[0.1, 0.2, -5.0]], (64, 1)) + np.random.default_rng(1).uniform(-1, 1, (64, 3)) * [1, 1, 0]
        d = np.tile([[0.0, 0.0, 1.0]], (64, 1))
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        dr.kernel_history()
        res = s.trace(o, d)
        dr.eval(res.t, res.t64, res.hit, res.evals, res.iterations, res.capped, res.unresolved)
        hist = dr.kernel_history()
        dr.set_flag(dr.JitFlag.KernelHistory, False)
        hashes.append(sorted(h["hash"] for h in hist if h.get("type") == dr.KernelType.JIT))
        # the hits are those of the surface with these values (closed form on
        # the ray x = x0, y = y0: z^2 = radius^2 - x0^2 - y0^2 - k x0 y0 + k)
        x0, y0 = o[:, 0].astype(np.float32).astype(np.float64), o[:, 1].astype(np.float32).astype(np.float64)
        q = r * r - x0 * x0 - y0 * y0 - k * x0 * y0 + k
        t_ref = np.where(q >= 0, 5.0 - np.sqrt(np.maximum(q, 0)), np.inf)
        hit = np.asarray(res.hit)
        assert np.array_equal(hit, np.isfinite(t_ref) & (t_ref > 0))
        assert np.allclose(np.asarray(res.t64)[hit], t_ref[hit], atol=1e-5)
    assert hashes[0] and hashes[0] == hashes[1]


@pytest.mark.parametrize("surface, key, values", [("blobs", "radius", (0.8, 0.9)),
                                                  ("torus", "R", (1.0, 1.5)),
                                                  ("spikes", "height", (1.0, 0.8))])
def test_library_parameter_update_keeps_kernels(surface, key, values):
    """A library parameter that also moves the surface's box (the blobs'
    radius) keeps the compiled kernels: the box centre enters as named
    constants. Oracle for the image: a fresh load with the new value (box
    filter: bit for bit)."""
    import drjit as dr
    import mitsuba as mi
    mi.set_variant(VARIANT)
    lgshape.register_plugins()

    def scene(value):
        return mi.load_dict({
            "type": "scene", "integrator": {"type": "lg_aov", "aovs": "dd:depth"},
            "sensor": {"type": "perspective",
                       "to_world": mi.ScalarTransform4f().look_at([0, -5, 2], [0, 0, 0], [0, 0, 1]),
                       "film": {"type": "hdrfilm", "width": 16, "height": 16,
                                "rfilter": {"type": "box"}}},
            "s": {"type": "lgsurface", "surface": surface, key: value}})

    def render(sc):
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        dr.kernel_history()
        img = mi.render(sc, spp=1)
        dr.eval(img)
        hist = dr.kernel_history()
        dr.set_flag(dr.JitFlag.KernelHistory, False)
        return np.array(img), sorted(h["hash"] for h in hist if h.get("type") == dr.KernelType.JIT)

    sc = scene(values[0])
    _, before = render(sc)
    params = mi.traverse(sc)
    params["s." + key] = values[1]
    params.update()
    img, after = render(sc)
    assert before and before == after
    fresh, _ = render(scene(values[1]))
    assert np.array_equal(img, fresh)
