"""The Dask side of :mod:`lgshape.frames` that needs ``distributed`` at import
(so that :mod:`lgshape.frames` itself does not)."""
from distributed import WorkerPlugin

from .plugins import use_variant


class WarmUp(WorkerPlugin):
    """Set up a worker before it renders: import Mitsuba, set the variant,
    register lgshape's plugins and import the ray tracer, in the worker's
    event loop, on every worker of the cluster, those that join later (a
    killed worker's replacement) included.

    Besides saving the first frame that time, this keeps Python source from
    being compiled in a task thread while the event loop compiles too: on
    CPython 3.11 two threads compiling at once can fail with ``SystemError:
    AST constructor recursion depth mismatch`` (Mitsuba's and Dr.Jit's
    imports parse source with :func:`ast.parse`). Errors are not raised
    here: the frames' tasks meet and report them."""

    def __init__(self, variant):
        self.variant = variant
        self.name = f"lgshape-warm-up-{variant}"

    def setup(self, worker):
        try:
            use_variant(self.variant)
            import lgshape.trace  # noqa: F401  (imported by the first lgsurface otherwise)
        except Exception:  # noqa: BLE001  (the frames' tasks raise it again, reported)
            pass
