"""Bad input, tried at random: every text, expression and property set ends
in a result or in one of lgshape's own errors, in bounded time.

A seeded generator writes expression texts from the grammar of
:mod:`lgshape.expr.parser` (numbers of every form, up to the float64
limits: 1e308, 1e-320, -0; variables, pi, e, named constants; every
operator and function, min/max of 2 to 4 arguments, powers), most of them
shifted by their value at a point of the box so that they have a zero
there, and mutates some (characters deleted, inserted, swapped or
doubled; parentheses unbalanced; numbers replaced by inf, nan, 1e999,
1e-400, 0x10; unknown names; unicode letters and spaces). Each goes
``parse -> Surface`` (a small random box, depth 2 or 3, a random search
mode) and, for some of those built, ``trace`` of a few rays; the same
expressions go through ``mi.load_dict`` as ``lgsurface`` properties, with
random values of the plugin's other properties.

The outcome must be one of:

- refused by :class:`lgshape.ParseError` (a position in the text) or
  ValueError (naming the parameter, the position or the limit);
- built (a nonzero constant f warns once, :class:`EmptySurfaceWarning`)
  and traced, with every hit a root and no root missed, by the float64
  oracle below.

Never another exception type, never a hang (every stage has an operation
bound: ``max_iterations``, the node limits of :mod:`lgshape.trace`; the
pytest timeout is a hang guard only).

Oracle for the traced rays (float64, independent of the search): F(t) =
f(o + t d) along the float32 ray in numpy float64. A hit at t64 is false
where F is finite, of one sign and above the noise floor NOISE64 (1 + M) on
a 33-point scan of [t64 - 2 tol, t64 + 2 tol] (M: max |F| over the ray's
segment in the box, tol the documented 1e-6 of the diagonal), or where its
sign change there is a pole (float64 bisection of it ends in a larger |F|
than it started with). For an f defined and continuous everywhere
(:func:`lgshape.trace._total`), a sign change of F between two of 257 scan
points before t64 - tol (both above the floor) is a root the search missed.
"""
import math
import warnings

import numpy as np
import pytest

import lgshape
from lgshape import ParseError, parse
from lgshape.arraymath import NUMPY
from lgshape.expr import evaluate
from lgshape.expr.node import constant_value
from lgshape.expr.parser import free_names
from lgshape.reference import along, clip_to_box
from lgshape.trace import MAX_FUSED_NODES, EmptySurfaceWarning, _total

NOISE64 = 1e-12      # the float64 floor of a proven sign (as tests/oracles.py)
REL_TOL = 1e-6       # the search's documented accuracy, x the box diagonal

FUNCS1 = ("sqrt", "exp", "log", "sin", "cos", "abs")
NUMBERS = ("0", "-0", "1", "2", "0.5", ".25", "3.", "1e-3", "2.5E+2", "1e308",
           "1.7976931348623157e308", "1e-320", "4.9e-324", "2.2250738585072014e-308", "123456789012345678901234567890",
           "0.1", "7", "1e2")
NAMES = ("a", "b", "radius")


def _number(rng):
    if rng.random() < 0.5:
        return str(NUMBERS[rng.integers(len(NUMBERS))])
    return f"{rng.uniform(-3, 3):.{int(rng.integers(1, 6))}g}"


def _expr(rng, depth):
    """A random text of the grammar (a tree of at most ``depth`` levels)."""
    r = rng.random()
    if depth <= 0 or r < 0.2:
        leaf = rng.random()
        if leaf < 0.55:
            return "xyz"[rng.integers(3)]
        if leaf < 0.65:
            return ("pi", "e")[rng.integers(2)]
        if leaf < 0.75:
            return NAMES[rng.integers(len(NAMES))]
        return _number(rng)
    a = _expr(rng, depth - 1)
    if r < 0.5:
        op = ("+", "-", "*", "/", "+", "*", "-")[rng.integers(7)]
        return f"({a} {op} {_expr(rng, depth - 1)})" if rng.random() < 0.6 else \
            f"{a}{op}{_expr(rng, depth - 1)}"
    if r < 0.62:
        n = (2, 2, 3, 4, -1, 0, 1, 6, 2.5, 1000, -3)[rng.integers(11)]
        return f"({a})^{n}" if rng.random() < 0.8 else f"{a}**{n}"
    if r < 0.85:
        return f"{FUNCS1[rng.integers(len(FUNCS1))]}({a})"
    if r < 0.95:
        k = int(rng.integers(2, 5))
        args = ", ".join([a] + [_expr(rng, depth - 1) for _ in range(k - 1)])
        return f"{('min', 'max')[rng.integers(2)]}({args})"
    return f"-{a}"


INSERTS = list("()+-*/^,.e0123456789xyz $#") + ["\u00e9", "\u2211", "\u00a0", "\t", "\n",
                                                  "inf", "nan", "1e999", "foo", "X", "sqrt",
                                                  "min(", ")"]
SWAPS = ("inf", "nan", "1e999", "1e-400", "-0", "0x10", "1e308*1e308", "Infinity", "foo",
         "e1", "1e", "..5")


def _mutate(rng, text):
    """``text`` with 1 to 3 random edits."""
    for _ in range(int(rng.integers(1, 4))):
        k = rng.integers(6)
        i = int(rng.integers(len(text) + 1))
        if k == 0 and text:                                 # delete
            text = text[:i] + text[i + 1:]
        elif k == 1:                                        # insert
            text = text[:i] + INSERTS[rng.integers(len(INSERTS))] + text[i:]
        elif k == 2 and len(text) > 1:                      # swap neighbours
            i = min(i, len(text) - 2)
            text = text[:i] + text[i + 1] + text[i] + text[i + 2:]
        elif k == 3:                                        # double a span
            j = int(rng.integers(i, len(text) + 1))
            text = text[:j] + text[i:j] + text[j:]
        elif k == 4:                                        # unbalance
            text = ("(" * int(rng.integers(1, 4)) + text) if rng.random() < 0.5 else \
                text + ")" * int(rng.integers(1, 4))
        else:                                               # a bad number or name
            text = text[:i] + SWAPS[rng.integers(len(SWAPS))] + text[i:]
    return text


def _constants(rng):
    """Values for the named constants: mostly plain numbers, some 0 (which
    may make f constant), a few not finite or not numbers (refused)."""
    out = {}
    for name in NAMES:
        r = rng.random()
        out[name] = (0.0 if r < 0.15 else float(rng.uniform(-2, 2)) if r < 0.97 else
                     (math.inf, math.nan, 1e308, -1e-320, "1")[rng.integers(5)])
    return out


def _box(rng):
    c = rng.uniform(-2, 2, 3) * (1e6 if rng.random() < 0.05 else 1)
    h = rng.uniform(0.3, 2, 3)
    if rng.random() < 0.2:
        h[rng.integers(3)] *= 1e-3                          # a flat box
    return c - h, c + h


def _shifted(rng, text, consts, lo, hi):
    """``text - v``, v its value at a random point of the box (a zero
    there), where that value is finite; else the text as it is."""
    try:
        f = parse(text, constants=consts)
    except ValueError:
        return text
    p = lo + (hi - lo) * rng.uniform(0.2, 0.8, 3)
    with np.errstate(all="ignore"):
        v = float(np.broadcast_to(evaluate(f, dict(zip("xyz", p)), NUMPY), ()))
    return f"{text} - ({v!r})" if math.isfinite(v) else text


def _cases(seed, n):
    """(text, constants, box, surface options) for n cases, one third
    mutated."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        lo, hi = _box(rng)
        consts = _constants(rng)
        text = _expr(rng, int(rng.integers(1, 5)))
        if rng.random() < 0.7:
            text = _shifted(rng, text, {c: v for c, v in consts.items()
                                        if isinstance(v, float) and math.isfinite(v)}, lo, hi)
        if k % 3 == 2:
            text = _mutate(rng, text)
        opts = {"depth": int(rng.integers(2, 4)), "max_iterations": 512}
        mode = rng.random()
        if mode < 0.1:
            opts["search"] = "taylor"
        elif mode < 0.15:
            opts["search"] = "global"
        out.append((text, consts, (lo, hi), opts))
    return out


def _kind(err) -> str:
    """The kind of a refusal, for the counts: its message's gist."""
    text = str(err)
    for key in ("unknown identifier", "unexpected character", "expected", "too large",
                "integer powers", "exponent", "identically 0", "NaN or infinite", "must be",
                "nodes, over the limit", "takes", "constant"):
        if key in text:
            return f"{type(err).__name__}: {key}"
    return f"{type(err).__name__}: other"


def _build(text, consts, box, opts):
    """parse -> Surface: ('built', surface, warned) or ('refused', kind)."""
    try:
        f = parse(text, constants=consts)
    except ParseError as err:
        assert "position" in str(err), str(err)
        return "refused", _kind(err)
    except ValueError as err:           # a bad constant: named in the message
        assert "constant" in str(err), str(err)
        return "refused", _kind(err)
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        try:
            s = lgshape.Surface(f, bbox=box, **opts)
        except ValueError as err:
            return "refused", _kind(err)
    empties = [w for w in said if issubclass(w.category, EmptySurfaceWarning)]
    assert len(empties) == (len(s.grid.cells) == 0), (text, [str(w.message) for w in said])
    c = constant_value(f)
    if c is not None:                   # a nonzero constant: no cells, said once
        assert c != 0 and len(s.grid.cells) == 0 and len(empties) == 1, (text, c)
    return "built", s


def _rays(rng, lo, hi, n):
    centre, ext = (lo + hi) / 2, hi - lo
    o = centre + ext * rng.normal(size=(n, 3)) * 1.5
    d = lo + ext * rng.uniform(0.1, 0.9, (n, 3)) - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return o.astype(np.float32), d.astype(np.float32)


def _check_rays(s, f, o32, d32):
    """Every hit a root, no root missed on a continuous f (see the module
    notes). Returns (hits, misses, rays the oracle could not judge)."""
    res = s.trace(o32, d32)
    hit, t64 = np.asarray(res.hit), np.asarray(res.t64, np.float64)
    assert np.all(np.isinf(t64[~hit])) and np.all(np.isfinite(t64[hit])), "t64 of hits and misses"
    o, d = o32.astype(np.float64), d32.astype(np.float64)

    def F(X, Y, Z):
        return np.broadcast_to(evaluate(f, {"x": X, "y": Y, "z": Z}, NUMPY), np.shape(X))
    diag = float(np.linalg.norm(s.hi - s.lo))
    tol = REL_TOL * diag / np.linalg.norm(d, axis=1)
    t0, t1 = clip_to_box(o, d, s.lo, s.hi)
    unjudged = 0
    with np.errstate(all="ignore"):
        for i in range(len(o)):
            oi, di = o[i:i + 1], d[i:i + 1]
            if not t1[i] > t0[i]:
                assert not hit[i], "a hit on a ray that misses the box"
                continue
            scan = np.linspace(t0[i], t1[i], 257)
            Fs = along(F, oi, di, scan[None])[0]
            M = np.max(np.abs(Fs[np.isfinite(Fs)]), initial=0.0)
            if not math.isfinite(M) or M > 1e300:
                unjudged += 1
                continue
            floor = NOISE64 * (1 + M)
            if hit[i]:
                w = 2 * tol[i]
                near = np.linspace(t64[i] - w, t64[i] + w, 33)
                Fn = along(F, oi, di, near[None])[0]
                if not np.all(np.isfinite(Fn)):
                    unjudged += 1                 # a domain's edge: not judged here
                    continue
                sign = np.sign(Fn)
                if np.all(np.abs(Fn) > floor) and np.all(sign == sign[0]):
                    raise AssertionError(f"false hit: t64 {t64[i]!r}, F there {Fn[16]!r} "
                                         f"(floor {floor:.3g}); ray {o32[i].tolist()} "
                                         f"{d32[i].tolist()}")
                k = np.flatnonzero(sign[:-1] * sign[1:] < 0)
                if len(k):                        # a sign change: a root, not a pole
                    a, b = near[k[0]], near[k[0] + 1]
                    start = min(abs(Fn[k[0]]), abs(Fn[k[0] + 1]))
                    fa = Fn[k[0]]
                    for _ in range(60):
                        m = 0.5 * (a + b)
                        fm = along(F, oi, di, np.array([[m]]))[0, 0]
                        if np.sign(fm) == np.sign(fa):
                            a, fa = m, fm
                        else:
                            b = m
                    end = min(abs(fa), abs(along(F, oi, di, np.array([[b]]))[0, 0]))
                    assert end <= start, f"a hit at a pole: t64 {t64[i]!r}"
            if _total(f):
                before = scan < (t64[i] - tol[i] if hit[i] else np.inf)
                strong = np.isfinite(Fs) & (np.abs(Fs) > floor)
                sign = np.where(strong, np.sign(Fs), 0)
                pair = (sign[:-1] * sign[1:] < 0) & before[1:]
                assert not pair.any(), (
                    f"missed root: sign change in [{scan[:-1][pair][0]!r}, "
                    f"{scan[1:][pair][0]!r}], hit {bool(hit[i])} t64 {t64[i]!r}; "
                    f"ray {o32[i].tolist()} {d32[i].tolist()}")
    return int(hit.sum()), int((~hit).sum()), unjudged


#: Counts of the last run of each test, for the note (``pytest -s`` prints them).
COUNTS: dict = {}


@pytest.mark.timeout(300)
def test01_texts_parse_build_trace():
    """600 random and mutated texts through parse -> Surface, and the
    first 24 built (with a zero in the box) traced with 6 rays each.
    Oracle: the float64 scan of the module notes; the outcome classes
    (refused by lgshape's errors, built, traced) are counted."""
    rng = np.random.default_rng(20)
    counts = {"cases": 0, "built": 0, "empty": 0, "traced": 0, "hits": 0, "misses": 0,
              "unjudged": 0}
    refused: dict = {}
    traced = 0
    for text, consts, box, opts in _cases(2020, 600):
        counts["cases"] += 1
        out = _build(text, consts, box, opts)
        if out[0] == "refused":
            refused[out[1]] = refused.get(out[1], 0) + 1
            continue
        s = out[1]
        counts["built"] += 1
        if len(s.grid.cells) == 0:
            counts["empty"] += 1
        if traced >= 24 or (len(s.grid.cells) == 0 and traced % 4):
            continue                              # (an empty one now and then)
        traced += 1
        o32, d32 = _rays(rng, s.lo, s.hi, 6)
        h, m, u = _check_rays(s, parse(text, constants=consts), o32, d32)
        counts["traced"] += 1
        counts["hits"] += h
        counts["misses"] += m
        counts["unjudged"] += u
    counts["refused"] = refused
    COUNTS["texts"] = counts
    print("\nfuzz texts:", counts)
    # the generator reaches every outcome (a test of the test)
    assert counts["built"] > 100 and counts["traced"] == 24 and counts["hits"] > 0
    assert sum(refused.values()) > 100 and counts["empty"] > 0


@pytest.mark.timeout(120)
@pytest.mark.parametrize("text", ["1", "e", "-e", "pi", "1e-300", "-1e-320", "sqrt(2)",
                                  "x*0 + 1", "a*x + 1", "exp(-1000) + 1e-300"])
def test02_constant_f_is_empty_everywhere(text):
    """A nonzero constant f (also one made constant by a named constant's
    value, a = 0) builds, warns once that it has no zero in the box, and
    every query misses: trace (frozen and traced), any-hit, intersect,
    occluded; normals and values are one per point. Oracle: a nonzero
    constant has no root (closed form)."""
    import drjit as dr
    f = parse(text, constants={"a": 0.0})
    assert constant_value(f) not in (None, 0.0)
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        s = lgshape.Surface(f, bbox=((-1,) * 3, (1,) * 3))
    assert [w.category for w in said] == [EmptySurfaceWarning]
    assert "no zero in the box" in str(said[0].message) and len(s.grid.cells) == 0
    o = np.float32([[0, 0, -3], [0.2, 0.1, 0], [5, 5, 5]])
    d = np.float32([[0, 0, 1], [1, 0, 0], [-1, -1, -1]])
    for freeze in (True, False):
        s.freeze = freeze
        r = s.trace(o, d)
        assert not np.asarray(r.hit).any() and np.all(np.isinf(np.asarray(r.t)))
        assert not np.asarray(s.trace(o, d, any_hit=True).hit).any()
        t, hit = s.intersect(o, d)
        assert not np.asarray(hit).any() and np.all(np.isinf(np.asarray(t)))
        assert not np.asarray(s.occluded(o, d, 10.0)).any()
    v = s.value(o)
    assert dr.width(v) == 3 and np.allclose(np.asarray(v), np.float32(constant_value(f)))
    assert dr.width(s.normal(o)) == 3


@pytest.mark.parametrize("text,consts", [("0", None), ("x - x", None), ("3*x - 3*x", None),
                                         ("a*x", {"a": 0.0}), ("a*sin(x) + b", {"a": 0, "b": 0}),
                                         ("min(x, a) - min(x, a)", {"a": 1.0})])
def test03_zero_f_is_refused(text, consts):
    """f identically 0 (every point would be on the surface, with no normal)
    is refused with a ValueError saying so, also where a named constant's
    value makes it 0. Oracle: the closed form f = 0."""
    with pytest.raises(ValueError, match="identically 0"):
        lgshape.Surface(parse(text, constants=consts), bbox=((-1,) * 3, (1,) * 3))


@pytest.mark.timeout(120)
def test04_size_limits_are_named(monkeypatch):
    """A sum of 20,001 equal terms builds at once (folded into one term by
    construction: 20001*x - 1, the closed form, checked exactly); a sum of
    n distinct terms evaluated whole in the kernel past
    MAX_FUSED_NODES is refused naming the limit and the size found, and so
    is any expression past MAX_NODES (here lowered to 100)."""
    from lgshape import trace
    monkeypatch.setattr(trace, "MAX_NODES", 100)
    text = " + ".join(f"sin({k + 1}*x)" for k in range(40))
    with pytest.raises(ValueError, match=r"f has \d+ nodes, over the limit of 100 .*MAX_NODES"):
        lgshape.Surface(text, bbox=((-1,) * 3, (1,) * 3))
    monkeypatch.undo()
    f = parse("+".join(["x"] * 20001) + "-1")
    assert f.size() == 5 and f.args[0].args[0].param == 20001.0    # sub, mul, 20001, x, 1
    s = lgshape.Surface(f, bbox=((-1,) * 3, (1,) * 3), depth=3)
    r = s.trace(np.float32([[-2, 0.1, 0.2]]), np.float32([[1, 0, 0]]))
    assert abs(float(np.asarray(r.t64)[0]) - (2 + 1 / 20001)) <= 1e-6 * s.diagonal
    n = MAX_FUSED_NODES // 4
    text = " + ".join(f"sin({k + 1}*x + {k % 7}*y)" for k in range(n)) + " - 0.5"
    with pytest.raises(ValueError, match=r"f has \d+ nodes, over the limit of 20000"):
        lgshape.Surface(text, bbox=((-1,) * 3, (1,) * 3), tables=False)


def _point(rng):
    """A bbox corner: mostly a plain point, some with NaN, inf or huge values."""
    p = [float(v) for v in rng.uniform(-2, 2, 3)]
    r = rng.random()
    if r < 0.08:
        p[rng.integers(3)] = (math.nan, math.inf, -math.inf, 1e308)[rng.integers(4)]
    return p


def _props(rng, text, consts):
    """lgsurface properties of the types its documentation gives (string,
    point, float, integer, boolean), with random values."""
    lo = _point(rng)
    hi = [v + float(rng.uniform(0.05, 2)) for v in lo] if rng.random() < 0.9 else _point(rng)
    props = {"type": "lgsurface", "expr": text, "bbox_min": lo, "bbox_max": hi}
    r = rng.random()
    if r < 0.1:
        del props["bbox_min"]
    elif r < 0.15:
        props["surface"] = ("torus", "sphere", "nope", "gyroid")[rng.integers(4)]
        del props["expr"]
    try:
        used = [n for n, _ in free_names(text)]
    except ParseError:
        used = []
    for name in NAMES:
        if name in used and isinstance(consts[name], float) and rng.random() < 0.9:
            props[name] = consts[name]
    for name, values in (("L", (-1.0, 0.0, 0.5, 100.0, math.nan, math.inf)),
                         ("G", (-1.0, 0.0, 1e-9, 100.0, math.nan)),
                         ("depth", (0, 1, 2, 3, 11, -5)),
                         ("flip_normals", (True, False)),
                         ("smoothness", (0.1, -1.0)), ("threshold", (0.5,)),
                         ("radiuss", (1.0,))):
        if rng.random() < 0.08:
            props[name] = values[rng.integers(len(values))]
    return props


@pytest.mark.timeout(300)
def test05_plugin_properties():
    """150 random lgsurface property sets (the texts of test01, named
    constants as float properties, random boxes, L, G, depth, flags, an
    unknown property now and then) through ``mi.load_dict``: each loads or
    is refused by lgshape's ParseError or a ValueError naming 'lgsurface'
    and what it refuses, or by Mitsuba's own property check naming the
    property. Oracle: the documented outcome classes (nothing is traced)."""
    mi = pytest.importorskip("mitsuba")
    from conftest import VARIANT
    mi.set_variant(VARIANT)
    lgshape.register_plugins()
    rng = np.random.default_rng(5)
    loaded, refused = 0, {}
    for text, consts, _, _ in _cases(77, 150):
        props = _props(rng, text, consts)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                mi.load_dict({"type": "scene", "s": props})
                loaded += 1
                continue
            except ParseError as err:
                assert "position" in str(err), str(err)
                kind = "ParseError"
            except ValueError as err:
                assert str(err).startswith("lgsurface"), str(err)
                kind = _kind(err).replace("ValueError: other", "ValueError: lgsurface")
            except RuntimeError as err:     # Mitsuba's own check of a property
                assert "property" in str(err), str(err)
                kind = "RuntimeError: property"
        refused[kind] = refused.get(kind, 0) + 1
    COUNTS["plugin"] = {"loaded": loaded, "refused": refused}
    print("\nfuzz plugin properties:", COUNTS["plugin"])
    assert loaded > 20 and sum(refused.values()) > 20
