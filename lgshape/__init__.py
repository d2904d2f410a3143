"""lgshape: guaranteed ray intersection with implicit surfaces (Kalra & Barr's
LG surfaces) for Mitsuba 3, vectorised with Dr.Jit.

Pipeline: expression (:mod:`lgshape.expr`) -> bounds (:mod:`lgshape.bounds`)
-> pruning grid (:mod:`lgshape.grid`) -> ray search (:mod:`lgshape.trace`)
-> Mitsuba plugins (:mod:`lgshape.plugins`). Only the plugins and the command
line import Mitsuba.
"""
from . import _llvm

_llvm.ensure()  # before anything imports drjit

from .expr import Expr, ParseError, parse  # noqa: E402
from .expr.node import var as _var  # noqa: E402

x, y, z = _var("x"), _var("y"), _var("z")

from . import surfaces  # noqa: E402
from .expr.node import cos, exp, log, maximum, minimum, sin, sqrt  # noqa: E402
from .expr.node import abs_ as abs  # noqa: E402,A001

__version__ = "0.1.0"


def __getattr__(name):
    if name == "Surface":
        from .trace import Surface
        return Surface
    if name == "register_plugins":
        from .plugins import register_plugins
        return register_plugins
    raise AttributeError(f"module 'lgshape' has no attribute {name!r}")


__all__ = ["Expr", "ParseError", "Surface", "abs", "cos", "exp", "log", "maximum", "minimum",
           "parse", "register_plugins", "sin", "sqrt", "surfaces", "x", "y", "z"]
