"""Array back ends for the evaluators: numpy (float64, host) and Dr.Jit.

The op table's rules are written once against this small namespace
(``sqrt``, ``select``, ``minimum``...), so the same rule evaluates numpy
float64 arrays (oracles, the pruning-grid build) and Dr.Jit arrays of any
backend (the ray kernel, LLVM or CUDA). ``eps`` is the relative outward
padding that interval results get to cover rounding; ``eps_t`` is the same for
the transcendental ops. ``const`` turns an
expression constant into an array (opaque in Dr.Jit, so that another value
does not recompile a kernel).
"""
from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass

import drjit as dr
import numpy as np


class NumpyMath:
    """float64 numpy arrays."""
    eps = 2.0 ** -51          # 2 ulp of float64: correctly rounded + - * / sqrt
    eps_t = 2.0 ** -46        # 64 ulp: libm's sin, cos, exp, log
    u = 2.0 ** -52            # unit roundoff (2^-53) with a factor 2 of margin
    tiny = 2.0 ** -1020       # underflow: above the largest subnormal step
    inf = math.inf
    sqrt, exp, log = staticmethod(np.sqrt), staticmethod(np.exp), staticmethod(np.log)
    sin, cos, abs = staticmethod(np.sin), staticmethod(np.cos), staticmethod(np.abs)
    floor, ceil, isnan = staticmethod(np.floor), staticmethod(np.ceil), staticmethod(np.isnan)
    isfinite = staticmethod(np.isfinite)
    minimum, maximum = staticmethod(np.minimum), staticmethod(np.maximum)
    select = staticmethod(np.where)

    def const(self, c: float):
        return np.float64(c)

    def named(self, name: str, c: float):
        return np.float64(c)

    @staticmethod
    def sincos(v):
        return np.sin(v), np.cos(v)

    @staticmethod
    def sincos32(v):
        """sin v and cos v computed in float32 (v rounded to float32)."""
        v32 = np.asarray(v).astype(np.float32)
        return np.sin(v32).astype(np.float64), np.cos(v32).astype(np.float64)

    def errstate(self):
        return np.errstate(all="ignore")

    @staticmethod
    def branch(cond, true_fn, false_fn, label=None):
        """true_fn()'s outputs where ``cond``, false_fn()'s elsewhere (a
        tuple of arrays each); numpy evaluates both."""
        return tuple(np.where(cond, a, b) for a, b in zip(true_fn(), false_fn()))


@dataclass(init=False, eq=False)
class DrJitMath:
    """Dr.Jit arrays of floating-point type ``Float`` (32 or 64 bit).

    A dataclass whose one field is its cache of opaque constants, so that a
    frozen function (``dr.freeze``) taking it as an input sees them."""
    inf = math.inf
    _consts: dict

    def __init__(self, Float, native=False, bound=None):
        """``native``: Dr.Jit's own functions on every backend (CUDA's
        multi-function unit too), for code that needs no error bound (the
        baselines); the bounds' ``eps_t`` does not hold for them on CUDA.
        ``bound``: name -> array, the values of named constants by name (for
        instance scene parameters with gradients, so that derivatives with
        respect to them flow through the expression); other named constants
        are opaque values of their own."""
        self.dr, self.Float = dr, Float
        self.bound = dict(bound or {})
        single = dr.type_v(Float) == dr.VarType.Float32
        # + - * / sqrt are correctly rounded (pad by 2 ulp); Dr.Jit's sin,
        # cos, exp and log are accurate to a few ulp (pad by 16 / 64 ulp).
        self.eps = 2.0 ** -22 if single else 2.0 ** -51
        self.eps_t = 2.0 ** -19 if single else 2.0 ** -46
        self.u = 2.0 ** -23 if single else 2.0 ** -52
        # Absolute slack for underflow: the smallest normal number. exp's
        # rule adds it (an exp that underflows, gradually or flushed to 0);
        # the other ops' underflow (a product below it) is outside the model.
        self.tiny = 2.0 ** -126 if single else 2.0 ** -1020
        self._consts: dict[float, object] = {}
        self.sqrt, self.exp, self.log = dr.sqrt, dr.exp, dr.log
        self.sin, self.cos, self.abs = dr.sin, dr.cos, dr.abs
        self._sincos = self._sincos32 = dr.sincos
        if not native and dr.backend_v(Float) == dr.JitBackend.CUDA:
            # CUDA's float32 sin, cos, exp and log run on the GPU's
            # multi-function unit (sin.approx, ex2.approx, lg2.approx), whose
            # errors are absolute and grow with |x|, with no documented bound
            # for large |x|. Measured on an H200: exp's relative error is
            # about |x| 2^-24 (the rounding of x log2(e)), above eps_t on 12%
            # of x in [-88, 88]; sin and cos stayed within e_periodic's
            # eps_t + 2 u |x| on [-300, 300], with a margin of 2. So all four
            # are computed in float64 (Dr.Jit's CEPHES code) and rounded
            # (sincos32's float32 sine and cosine too, at any precision).
            self._sincos32 = _via_float64(dr.float32_array_t(Float), dr.sincos)
            if single:
                self.sin, self.cos, self.exp, self.log = (
                    _via_float64(Float, f) for f in (dr.sin, dr.cos, dr.exp, dr.log))
                self._sincos = _via_float64(Float, dr.sincos)
        self.floor, self.ceil, self.isnan, self.isfinite = dr.floor, dr.ceil, dr.isnan, dr.isfinite
        self.minimum, self.maximum, self.select = dr.minimum, dr.maximum, dr.select

    def sincos(self, v):
        return self._sincos(v)

    def sincos32(self, v):
        """sin v and cos v computed in float32 (v rounded to float32), in
        v's type."""
        s, c = self._sincos32(self.dr.float32_array_t(type(v))(v))
        return type(v)(s), type(v)(c)

    def const(self, c: float):
        v = self._consts.get(c)
        if v is None:
            v = self._consts[c] = self.dr.opaque(self.Float, c)
        return v

    def named(self, name: str, c: float):
        """A named constant: its own opaque value, never shared with a
        constant that happens to have the same value (so the kernel's code
        does not depend on the values); a ``bound`` one's given array."""
        if name in self.bound:
            return self.bound[name]
        key = ("named", name, c)
        v = self._consts.get(key)
        if v is None:
            v = self._consts[key] = self.dr.opaque(self.Float, c)
        return v

    def errstate(self):
        return contextlib.nullcontext()

    def branch(self, cond, true_fn, false_fn, label=None):
        """true_fn()'s outputs where ``cond``, false_fn()'s elsewhere (a
        tuple of arrays each): a symbolic conditional, whose true branch a
        SIMD packet (or a GPU warp) runs only where one of its lanes takes
        it. Both functions read their inputs from the enclosing scope; an
        array first made inside a branch (a literal such as 0 * x) must not
        be used after it: make such values before."""
        dr = self.dr
        return tuple(dr.if_stmt(args=(), cond=self.dr.mask_t(self.Float)(cond),
                                true_fn=lambda: tuple(true_fn()),
                                false_fn=lambda: tuple(false_fn()), label=label))


NUMPY = NumpyMath()


def zero_like(v):
    """0 of v's shape and type: for a Dr.Jit array a literal zero (what
    ``0.0 * v`` gives under Dr.Jit's fast math, also inside
    :func:`exact_arithmetic`, where the product would be traced and be NaN
    for an infinite v); for anything else ``0.0 * v`` (numpy: NaN where v
    is, as the float64 oracles always had it)."""
    if type(v).__module__.startswith("drjit"):
        return dr.zeros(type(v), dr.width(v))
    return 0.0 * v


def _via_float64(Float, fn):
    """fn computed in float64 and rounded to ``Float`` (one array or a
    tuple of them)."""
    Float64 = dr.float64_array_t(Float)

    def wrapped(v):
        out = fn(Float64(v))
        return tuple(Float(w) for w in out) if isinstance(out, tuple) else Float(out)
    return wrapped


def exact_arithmetic(Float):
    """A context in which Dr.Jit's float32 division and square root are
    IEEE's (correctly rounded), as the error model assumes: on CUDA, Dr.Jit's
    default fast-math mode makes them div.approx / sqrt.approx (2 ulp, and
    div.approx returns 0 for divisors above 2^126); the flag is read when an
    operation is traced, so the search is traced inside this context. LLVM's
    ``/`` and sqrt are IEEE's either way (nothing to do there).

    Fast math off also keeps ``0.0 * x`` a product (NaN for an infinite x):
    the rules make their zeros with :func:`zero_like`, the literal either
    way. Not covered, on any backend: ``dr.rcp`` and ``dr.rsqrt`` (approximate
    under fast math; the search uses neither) and ``x / c`` for a literal c,
    which Dr.Jit traces as x times the rounded 1 / c (two roundings, within
    ``u``, twice the unit roundoff)."""

    if dr.backend_v(Float) == dr.JitBackend.CUDA:
        return dr.scoped_set_flag(dr.JitFlag.FastMath, False)
    return contextlib.nullcontext()


def math_for(value):
    """The back end for an array (numpy -> NUMPY, Dr.Jit -> DrJitMath)."""
    if dr.is_array_v(value):
        return DrJitMath(dr.float_array_t(dr.leaf_t(value)) if dr.depth_v(value) > 1 else type(value))
    return NUMPY


def powi(v, n: int, mul=None):
    """v ** n for an integer n >= 1 by binary exponentiation (any array
    type; ``mul``: the product to use, default ``*``)."""
    mul = mul or (lambda a, b: a * b)
    result, base = None, v
    while n:
        if n & 1:
            result = base if result is None else mul(result, base)
        n >>= 1
        if n:
            base = mul(base, base)
    return result
