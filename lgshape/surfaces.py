"""The named surface library.

Each function returns an :class:`Implicit`: the expression f (surface f = 0,
f < 0 inside where that has a meaning) and a default bounding box. Several of
these algebraic surfaces are unbounded; their box is the usual clipping
region in which they are shown.

A function's sizes (radii, half sizes, widths: its attribute ``sizes``)
must be positive; a value <= 0 raises ValueError naming the surface, the
parameter and the value (``sphere: radius must be > 0, got -1``), as do the
other values a surface cannot take (a gyroid's ``scale`` 0, a Kummer
surface's ``mu2`` 3).
"""
from __future__ import annotations

import functools
import inspect
import math
from dataclasses import dataclass

from .expr.node import Expr, exp, sin, cos, minimum, var

x, y, z = var("x"), var("y"), var("z")

Box = tuple[tuple[float, float, float], tuple[float, float, float]]


@dataclass(frozen=True)
class Implicit:
    """A named implicit surface: ``expr`` = 0 inside ``bbox``."""
    name: str
    expr: Expr
    bbox: Box

    def __repr__(self):
        return f"Implicit({self.name!r}, bbox={self.bbox})"


def _cube(h: float) -> Box:
    return ((-h, -h, -h), (h, h, h))


def _sizes(*names):
    """Declare a library function's size parameters (``fn.sizes``) and
    refuse a value <= 0 for any of them before f is built."""
    def wrap(fn):
        signature = inspect.signature(fn)

        @functools.wraps(fn)
        def checked(*args, **kwargs):
            bound = signature.bind(*args, **kwargs)
            bound.apply_defaults()
            for name in names:
                _require(fn.__name__, name, bound.arguments[name], lambda v: v > 0, "> 0")
            return fn(*args, **kwargs)
        checked.sizes = names
        return checked
    return wrap


def _require(surface, name, value, ok, what):
    """ValueError unless ``ok(value)`` (a number or a named constant; an
    expression of Python's API is not checked)."""
    if isinstance(value, Expr) and value.op != "named":
        return
    if not ok(_number(value)):
        raise ValueError(f"{surface}: {name} must be {what}, got {_number(value):g}")


@_sizes("radius")
def sphere(radius: float = 1.0) -> Implicit:
    """Sphere x^2 + y^2 + z^2 - r^2."""
    return Implicit("sphere", x**2 + y**2 + z**2 - radius**2, _cube(1.1 * radius))


@_sizes("R", "r")
def torus(R: float = 1.0, r: float = 0.4) -> Implicit:
    """Torus around the z axis: (x^2 + y^2 + z^2 + R^2 - r^2)^2 - 4 R^2 (x^2 + y^2)."""
    q = x**2 + y**2
    e = (q + z**2 + (R**2 - r**2))**2 - 4 * R**2 * q
    h = 1.1 * (R + r)
    return Implicit("torus", e, ((-h, -h, -1.2 * r), (h, h, 1.2 * r)))


def tangle(c: float = 11.8) -> Implicit:
    """Tangle cube: x^4 - 5x^2 + y^4 - 5y^2 + z^4 - 5z^2 + 11.8."""
    e = x**4 - 5 * x**2 + y**4 - 5 * y**2 + z**4 - 5 * z**2 + c
    return Implicit("tangle", e, _cube(2.5))


def barth_sextic() -> Implicit:
    """Barth sextic (65 nodes), with phi the golden ratio:
    4 (phi^2 x^2 - y^2)(phi^2 y^2 - z^2)(phi^2 z^2 - x^2)
    - (1 + 2 phi)(x^2 + y^2 + z^2 - 1)^2. Unbounded; shown in [-1.6, 1.6]^3."""
    p2 = ((1 + math.sqrt(5)) / 2) ** 2
    phi = (1 + math.sqrt(5)) / 2
    x2, y2, z2 = x**2, y**2, z**2
    e = 4 * (p2 * x2 - y2) * (p2 * y2 - z2) * (p2 * z2 - x2) - (1 + 2 * phi) * (x2 + y2 + z2 - 1)**2
    return Implicit("barth_sextic", e, _cube(1.6))


def kummer(mu2: float = 1.69) -> Implicit:
    """Kummer quartic (16 nodes): (x^2 + y^2 + z^2 - mu^2)^2 - lambda p q r s with
    lambda = (3 mu^2 - 1) / (3 - mu^2), p = 1 - z - sqrt2 x, q = 1 - z + sqrt2 x,
    r = 1 + z + sqrt2 y, s = 1 + z - sqrt2 y; mu^2 = 1.69. Shown in [-2.2, 2.2]^3."""
    _require("kummer", "mu2", mu2, lambda v: v != 3,
             "other than 3 (lambda = (3 mu^2 - 1) / (3 - mu^2) would be infinite)")
    lam = (3 * mu2 - 1) / (3 - mu2)
    s2 = math.sqrt(2.0)
    p, q = 1 - z - s2 * x, 1 - z + s2 * x
    r, s = 1 + z + s2 * y, 1 + z - s2 * y
    e = (x**2 + y**2 + z**2 - mu2)**2 - lam * p * q * r * s
    return Implicit("kummer", e, _cube(2.2))


def _chebyshev6(u: Expr) -> Expr:
    u2 = u**2
    return 32 * u2**3 - 48 * u2**2 + 18 * u2 - 1


def chmutov6() -> Implicit:
    """Chmutov surface of degree 6: T6(x) + T6(y) + T6(z), with the Chebyshev
    polynomial T6(u) = 32u^6 - 48u^4 + 18u^2 - 1."""
    return Implicit("chmutov6", _chebyshev6(x) + _chebyshev6(y) + _chebyshev6(z), _cube(1.1))


def clebsch() -> Implicit:
    """Clebsch diagonal cubic: 81(x^3 + y^3 + z^3) - 189(x^2 y + x^2 z + y^2 x + y^2 z
    + z^2 x + z^2 y) + 54 xyz + 126(xy + xz + yz) - 9(x^2 + y^2 + z^2) - 9(x + y + z) + 1.
    Unbounded; shown in [-1.2, 1.2]^3."""
    e = (81 * (x**3 + y**3 + z**3)
         - 189 * (x**2 * y + x**2 * z + y**2 * x + y**2 * z + z**2 * x + z**2 * y)
         + 54 * x * y * z + 126 * (x * y + x * z + y * z) - 9 * (x**2 + y**2 + z**2)
         - 9 * (x + y + z) + 1)
    return Implicit("clebsch", e, _cube(1.2))


def wyvill_kernel(u: Expr) -> Expr:
    """Wyvill's soft-object kernel of u = r^2 / R^2 (clamped at u = 1, where it
    reaches 0 with zero slope): 1 - 4/9 u^3 + 17/9 u^2 - 22/9 u."""
    u = minimum(u, 1.0)
    return 1 - (4 / 9) * u**3 + (17 / 9) * u**2 - (22 / 9) * u


@_sizes("radius")
def blobs(centers=((-0.45, 0.0, 0.0), (0.45, 0.0, 0.0), (0.0, 0.55, 0.2)),
          radius: float = 1.0, threshold: float = 0.5) -> Implicit:
    """Wyvill soft objects: threshold - sum_i kernel(|p - c_i|^2 / R^2)."""
    total = None
    for cx, cy, cz in centers:
        u = ((x - cx)**2 + (y - cy)**2 + (z - cz)**2) / radius**2
        k = wyvill_kernel(u)
        total = k if total is None else total + k
    lo = tuple(min(c[i] for c in centers) - radius for i in range(3))
    hi = tuple(max(c[i] for c in centers) + radius for i in range(3))
    return Implicit("blobs", threshold - total, (lo, hi))


@_sizes("half_size")
def gyroid(scale: float = 2.0, half_size: float = 1.5) -> Implicit:
    """Gyroid: sin(s x) cos(s y) + sin(s y) cos(s z) + sin(s z) cos(s x)."""
    _require("gyroid", "scale", scale, lambda v: v != 0, "nonzero (f would be 0 everywhere)")
    X, Y, Z = scale * x, scale * y, scale * z
    e = sin(X) * cos(Y) + sin(Y) * cos(Z) + sin(Z) * cos(X)
    return Implicit("gyroid", e, _cube(half_size))


SPIKE_AXES = tuple(
    [(1, 0, 0), (0, 1, 0), (0, 0, 1)]
    + [tuple(s / math.sqrt(3) for s in (a, b, 1)) for a in (1, -1) for b in (1, -1)])


@_sizes("core", "width")
def spikes(core: float = 0.5, height: float = 1.0, width: float = 0.01,
           axes=SPIKE_AXES) -> Implicit:
    """A ball of radius ``core`` with 14 needle-thin spikes (seven lines through
    the centre), after the seed's stability example:
    x^2 + y^2 + z^2 - core^2 - height * sum_k exp(-rho_k^2 / width^2), where rho_k
    is the distance to the k-th axis line (|p x a_k|). A spike reaches |p| =
    sqrt(core^2 + height) and is at most ~2 width thick, thinner than a grid
    cell or a marcher's step."""
    r2 = x**2 + y**2 + z**2
    total = None
    for a in axes:
        # |p x a|^2 as a sum of squares: tight intervals, no cancellation.
        c = (a[1] * z - a[2] * y, a[2] * x - a[0] * z, a[0] * y - a[1] * x)
        rho2 = None
        for ci in c:
            if not ci.is_const:
                rho2 = ci**2 if rho2 is None else rho2 + ci**2
        term = exp(rho2 * (-1.0 / width**2))
        total = term if total is None else total + term
    h = 1.05 * math.sqrt(_number(core)**2 + max(_number(height), 0.0))
    return Implicit("spikes", r2 - core**2 - height * total, _cube(h))


def _number(v) -> float:
    """A parameter's value (a number, or a named constant of a scene)."""
    return v.param[1] if isinstance(v, Expr) and v.op == "named" else float(v)


#: Each library function's size parameters (all must be > 0).
SIZES = {}


#: Library surfaces by name (for the XML plugin's ``surface`` parameter).
LIBRARY = {f.__name__: f for f in (sphere, torus, tangle, barth_sextic, kummer, chmutov6,
                                   clebsch, blobs, gyroid, spikes)}
SIZES.update((name, getattr(fn, "sizes", ())) for name, fn in LIBRARY.items())
