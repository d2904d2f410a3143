"""Shared cases for the numbered tests: one expression per op of the op
table (so a new op row is picked up) and the surface library."""
import importlib
import os

import lgshape  # noqa: F401  (sets up libLLVM before drjit is imported)
import numpy as np
import pytest

from lgshape.expr import node as N
from lgshape.expr.ops import OPS
from lgshape.surfaces import LIBRARY

# The Mitsuba variant the suite runs on: llvm_ad_rgb, or another JIT variant
# (LGSHAPE_TEST_VARIANT=cuda_ad_rgb on a machine with a GPU); JIT and JIT_AD
# are the matching Dr.Jit modules (drjit.llvm / drjit.llvm.ad, or CUDA's).
VARIANT = os.environ.get("LGSHAPE_TEST_VARIANT", "llvm_ad_rgb")
JIT = importlib.import_module("drjit.cuda" if VARIANT.startswith("cuda") else "drjit.llvm")
JIT_AD = importlib.import_module(JIT.__name__ + ".ad")
if VARIANT != "llvm_ad_rgb":
    import mitsuba
    mitsuba.set_variant(VARIANT)     # numpy rays then go to its backend (trace.default_array3f)
if VARIANT.startswith("cuda"):
    # The rules' own tests (intervals, forms, point errors) run outside the
    # search; give them the arithmetic the search is traced with
    # (arraymath.exact_arithmetic). test_17 checks that context itself.
    import drjit as _dr
    _dr.set_flag(_dr.JitFlag.FastMath, False)

x, y, z = N.var("x"), N.var("y"), N.var("z")
u = x * y - z + 0.3          # a non-trivial argument, so composition is exercised


def op_case(name):
    """An expression that applies op `name` (one per row of the op table)."""
    arity = OPS[name].arity
    if name == "pow":
        return (x - 0.5 * y) ** 3 + (u ** 4) * z ** 2
    if name in ("sqrt", "log"):
        return getattr(N, name)(x * x + y * y + 0.2 * z * z + 0.05)
    if name == "div":
        return (x + y) / (z * z + 0.5) + u / (x * x + 1)
    builders = {"add": N.add, "sub": N.sub, "mul": N.mul, "neg": N.neg, "exp": N.exp,
                "sin": N.sin, "cos": N.cos, "abs": N.abs_, "min": N.minimum, "max": N.maximum,
                "step": N.step, "kink": N.kink}
    make = builders[name]
    return make(u, N.sin(y) * z + x) if arity == 2 else make(u * 1.5)


OP_NAMES = sorted(OPS)
SURFACE_NAMES = sorted(LIBRARY)
ALL_CASES = [("op", n) for n in OP_NAMES] + [("surface", n) for n in SURFACE_NAMES]


def case_expr(kind, name):
    if kind == "op":
        return op_case(name), ((-1.5, -1.5, -1.5), (1.5, 1.5, 1.5))
    s = LIBRARY[name]()
    return s.expr, s.bbox


def case_id(case):
    return f"{case[0]}-{case[1]}"


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


def random_boxes(rng, bbox, n, max_frac=0.3):
    """n random sub-boxes of bbox with edges up to max_frac of its size."""
    lo, hi = np.asarray(bbox[0]), np.asarray(bbox[1])
    size = (hi - lo) * rng.uniform(1e-3, max_frac, (n, 3)) * rng.uniform(0, 1, (n, 1)) ** 2
    blo = lo + (hi - lo - size) * rng.uniform(0, 1, (n, 3))
    return blo, blo + size


def sensor_xml(origin, target="0, 0, 0", up="0, 1, 0", fov="40", width="$res", height="$res",
               spp="$spp"):
    """The perspective sensor of the tests' scenes: a box-filtered hdrfilm
    and the independent sampler (values may be $-references to defaults)."""
    return f"""<sensor type="perspective">
        <float name="fov" value="{fov}"/>
        <transform name="to_world"><lookat origin="{origin}" target="{target}" up="{up}"/></transform>
        <sampler type="independent"><integer name="sample_count" value="{spp}"/></sampler>
        <film type="hdrfilm">
            <integer name="width" value="{width}"/><integer name="height" value="{height}"/>
            <rfilter type="box"/>
        </film>
    </sensor>"""


# --- Diagnostics for CI, whose log keeps only its tail ---------------------
# Each test's node id is written to .pytest_cache/lgshape-current-test when
# it starts (the Makefile prints it when pytest dies of a signal), and the
# innermost exception of every failure is repeated at the end of the run
# (Dr.Jit's loops re-raise "encountered an exception (see above)", whose
# cause the tail would lose).
_CURRENT = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                        ".pytest_cache", "lgshape-current-test")
_ROOT_CAUSES = []


def pytest_runtest_logstart(nodeid, location):
    try:
        os.makedirs(os.path.dirname(_CURRENT), exist_ok=True)
        with open(_CURRENT, "w") as f:
            f.write(nodeid + "\n")
    except OSError:
        pass


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    if report.failed and call.excinfo is not None:
        exc, seen = call.excinfo.value, set()
        chain = []
        while exc is not None and id(exc) not in seen:
            seen.add(id(exc))
            chain.append(f"{type(exc).__name__}: {str(exc).strip()[:600]}")
            exc = exc.__cause__ or exc.__context__
        if len(chain) > 1:
            _ROOT_CAUSES.append((item.nodeid, chain[-1]))


def pytest_terminal_summary(terminalreporter):
    if _ROOT_CAUSES:
        terminalreporter.section("innermost exceptions of the failures")
        for nodeid, cause in _ROOT_CAUSES:
            terminalreporter.write_line(f"{nodeid}: {cause}")
