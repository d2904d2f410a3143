"""The benchmark: lgshape against the usual ways of rendering an implicit
surface (sphere tracing, marching, Mitsuba's sdfgrid, a marching-cubes
mesh), speed against accuracy.

Run it all with ``lgshape bench [--quick] --out DIR`` (:func:`main`, the
parser and driver in :mod:`lgshape.bench.driver`); it writes
DIR/results.json, DIR/charts/ and DIR/BENCHMARKS.md
(:mod:`lgshape.bench.report`). Its sections:

- accuracy on primary rays and the stability suite
  (:mod:`lgshape.bench.accuracy`, with :mod:`lgshape.bench.stability`);
- speed: camera, incoherent and shadow rays, a render, first-image latency
  (:mod:`lgshape.bench.speed`; alone: ``python -m lgshape.bench.speed
  --out DIR [--quick]``);
- scale: cost against the number of primitives (:mod:`lgshape.bench.scale`);
- temporal stability under animation (:mod:`lgshape.bench.temporal`; alone:
  ``python -m lgshape.bench.temporal --out DIR [--quick]``).

They share :mod:`lgshape.bench.common` (rays, runners, timing) and
:mod:`lgshape.bench.baselines` (the other methods). Tools beside them:
``python -m lgshape.bench.trace_speed`` (lgshape's kernel against the
sphere tracer) and ``python -m lgshape.bench.kernel_profile SURFACE``
(where the kernel spends its cycles).
"""


def main(argv=None) -> int:
    """``lgshape bench ARGS``: see :func:`lgshape.bench.driver.main`."""
    # Late: the sections' fresh processes (the scale worker, the probe) import
    # this package, and time their own imports.
    from . import driver
    return driver.main(argv)
