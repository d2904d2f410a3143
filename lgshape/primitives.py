"""Many primitives from numpy arrays: unions, smooth unions and blends.

    import lgshape.primitives as P
    f = P.union(P.spheres(centres, radii), P.boxes(centres2, half_sizes))
    surf = lgshape.Surface(f)             # the box comes from the primitives

Each part holds one kind of primitive with one row of parameters per
primitive; the combinations return a :class:`~lgshape.tables.TableForm`
(templates and tables), so the kernel's code depends on the kinds used, not
on their number, and each pruning cell evaluates only the primitives that
can matter there.

Parameters are stored as float32 values (as Mitsuba's scene data); f is
defined by those. Kinds, as signed distances d (negative inside):

- ``spheres(c, r)``: |p - c| - r
- ``capsules(a, b, r)``: distance to the segment ab, minus r
- ``boxes(c, h, rounding=0)``: the box c +- h (half sizes h), its edges
  rounded by ``rounding`` (h is the outer extent)
- ``tori(c, R, r)``: the torus about the z axis through c, radii R > r

Combinations:

- ``union(*parts)``: min of the distances;
- ``smooth_union(*parts, k)``: the polynomial smooth minimum of radius k,
  folded over the primitives in order (parts first to last);
- ``blend(*parts, threshold=0.5)``: a soft object, f = threshold -
  sum_i w_i K(d_i / R_i) with the compactly supported kernel
  K(q) = max(0, 1 - q^2)^3, d_i the distance to the primitive's skeleton
  (the centre of a sphere, the segment of a capsule, the box, the circle of a
  torus) and R_i its radius of influence (the part's radius argument; for
  boxes ``rounding``). f < 0 inside.

:func:`load` reads a primitives file (one primitive per line, see there).
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from .expr.node import Expr, const, maximum, minimum, named, sqrt, var
from .tables import Aggregate, TableForm, make_group, param, smin_below, substitute

X, Y, Z = var("x"), var("y"), var("z")

#: Parameter columns of each kind, in a primitives file's order.
COLUMNS = {
    "sphere": ("cx", "cy", "cz", "r"),
    "capsule": ("ax", "ay", "az", "bx", "by", "bz", "r"),
    "box": ("cx", "cy", "cz", "hx", "hy", "hz", "rounding"),
    "torus": ("cx", "cy", "cz", "R", "r"),
}


@dataclass
class Part:
    """Primitives of one kind: ``kind`` and ``rows`` (n, len(COLUMNS[kind]))
    float64, with optional blend weights (n,)."""
    kind: str
    rows: np.ndarray
    weights: np.ndarray | None = None

    def __post_init__(self):
        cols = COLUMNS[self.kind]
        self.rows = np.asarray(self.rows, np.float64).reshape(-1, len(cols))
        if not np.all(np.isfinite(self.rows)):
            bad = int(np.argwhere(~np.all(np.isfinite(self.rows), 1))[0, 0])
            raise ValueError(f"{self.kind} {bad}: parameters must be finite, got {self.rows[bad]}")
        r = self.rows
        radius = {"sphere": [3], "capsule": [6], "torus": [3, 4], "box": [3, 4, 5]}[self.kind]
        for q in radius:
            bad = np.flatnonzero(~(r[:, q] > 0))
            if len(bad):
                raise ValueError(f"{self.kind} {bad[0]}: {cols[q]} must be positive, got {r[bad[0], q]}")
        if self.kind == "torus" and np.any(r[:, 4] >= r[:, 3]):
            raise ValueError(f"torus {np.flatnonzero(r[:, 4] >= r[:, 3])[0]}: r must be smaller than R")
        if self.kind == "box" and np.any((r[:, 6] < 0) | (r[:, 6] > r[:, 3:6].min(1))):
            raise ValueError(f"box {np.flatnonzero((r[:, 6] < 0) | (r[:, 6] > r[:, 3:6].min(1)))[0]}: "
                             "rounding must be between 0 and the smallest half size")
        if self.weights is not None:
            self.weights = np.broadcast_to(np.asarray(self.weights, np.float64), len(self.rows)).copy()

    def __len__(self):
        return len(self.rows)

    def extent(self):
        """(lo, hi) of the union of the primitives' boxes."""
        r = self.rows
        if self.kind == "sphere":
            c, e = r[:, :3], r[:, 3:4]
        elif self.kind == "capsule":
            lo = np.minimum(r[:, :3], r[:, 3:6]) - r[:, 6:7]
            hi = np.maximum(r[:, :3], r[:, 3:6]) + r[:, 6:7]
            return lo.min(0), hi.max(0)
        elif self.kind == "box":
            c, e = r[:, :3], r[:, 3:6]
        else:
            c, e = r[:, :3], np.stack([r[:, 3] + r[:, 4]] * 2 + [r[:, 4]], 1)
        return (c - e).min(0), (c + e).max(0)


def _check_positive(kind, name, v):
    v = np.asarray(v, np.float64)
    if np.any(~(v > 0)):
        i = int(np.argwhere(~(np.broadcast_to(v, v.shape) > 0).reshape(-1))[0, 0])
        raise ValueError(f"{kind} {i}: {name} must be positive, got {v.reshape(-1)[i]}")
    return v


def _n3(name, a):
    a = np.asarray(a, np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{name} must be an (N, 3) array, got shape {a.shape}")
    return a


def _col(n, v, name, kind):
    v = np.broadcast_to(np.asarray(v, np.float64), (n,))
    return _check_positive(kind, name, v)


def spheres(centres, radii, weights=None) -> Part:
    c = _n3("centres", centres)
    return Part("sphere", np.column_stack([c, _col(len(c), radii, "radius", "sphere")]), weights)


def capsules(a, b, radii, weights=None) -> Part:
    a, b = _n3("a", a), _n3("b", b)
    if len(a) != len(b):
        raise ValueError(f"a has {len(a)} rows, b has {len(b)}")
    return Part("capsule", np.column_stack([a, b, _col(len(a), radii, "radius", "capsule")]),
                weights)


def boxes(centres, half_sizes, rounding=0.0, weights=None) -> Part:
    c = _n3("centres", centres)
    h = np.broadcast_to(np.asarray(half_sizes, np.float64), c.shape)
    _check_positive("box", "half size", h)
    rr = np.broadcast_to(np.asarray(rounding, np.float64), (len(c),))
    if np.any(rr < 0) or np.any(rr > h.min(1)):
        raise ValueError("box rounding must be between 0 and the smallest half size")
    return Part("box", np.column_stack([c, h, rr]), weights)


def tori(centres, R, r, weights=None) -> Part:
    c = _n3("centres", centres)
    R, r = _col(len(c), R, "R", "torus"), _col(len(c), r, "r", "torus")
    if np.any(r >= R):
        raise ValueError("torus: r must be smaller than R")
    return Part("torus", np.column_stack([c, R, r]), weights)


# ---------------------------------------------------------------------------
# Templates: distance (and blend kernel) of each kind, in parameters p0, p1...
# ---------------------------------------------------------------------------

def _p(*qs):
    return [param(q) for q in qs]


def _centre_offset(q0=0):
    cx, cy, cz = _p(q0, q0 + 1, q0 + 2)
    return X - cx, Y - cy, Z - cz


def _sq(a):
    return a * a


def _distance(kind: str):
    """(template of the signed distance, its parameter columns); for the
    blend, (template of the skeleton distance, columns, radius column)."""
    if kind == "sphere":
        dx, dy, dz = _centre_offset()
        return sqrt(_sq(dx) + _sq(dy) + _sq(dz)) - param(3)
    if kind == "capsule":
        # p3..p5 = b - a, p6 = 1 / |b - a|^2 (computed per row), p7 = r
        dx, dy, dz = _centre_offset()
        bx, by, bz = _p(3, 4, 5)
        h = minimum(maximum((dx * bx + dy * by + dz * bz) * param(6), 0.0), 1.0)
        return sqrt(_sq(dx - bx * h) + _sq(dy - by * h) + _sq(dz - bz * h)) - param(7)
    if kind == "box":
        # p3..p5 = h - rounding, p6 = rounding
        dx, dy, dz = _centre_offset()
        q = [abs(v) - param(3 + i) for i, v in enumerate((dx, dy, dz))]
        outside = sqrt(sum(_sq(maximum(v, 0.0)) for v in q[1:]) + _sq(maximum(q[0], 0.0)))
        # min(0, max q): at max q = 0 (a sharp box's faces) min's slope is
        # max q's (its rule takes the second argument's at a tie), and the
        # outside term's is 0 there (tables.point_slope): grad f = +-e_i
        return outside + minimum(0.0, maximum(q[0], q[1], q[2])) - param(6)
    if kind == "torus":
        dx, dy, dz = _centre_offset()
        return sqrt(_sq(sqrt(_sq(dx) + _sq(dy)) - param(3)) + _sq(dz)) - param(4)
    raise ValueError(f"unknown primitive kind {kind!r} (one of {', '.join(COLUMNS)})")


def _distance_params(part: Part) -> np.ndarray:
    r = part.rows
    if part.kind == "capsule":
        ba = r[:, 3:6] - r[:, :3]
        L2 = (ba ** 2).sum(1)
        inv = np.where(L2 > 0, 1.0 / np.where(L2 > 0, L2, 1.0), 0.0)
        return np.column_stack([r[:, :3], ba, inv, r[:, 6]])
    if part.kind == "box":
        return np.column_stack([r[:, :3], r[:, 3:6] - r[:, 6:7], r[:, 6]])
    return r


def _kernel(kind: str, weighted: bool):
    """Blend kernel w K(d / R) with d the skeleton distance; parameters:
    the distance's (radius column = R), then w when weighted."""
    if kind == "sphere":
        dx, dy, dz = _centre_offset()
        d2 = _sq(dx) + _sq(dy) + _sq(dz)
    else:
        d = _distance(kind)                 # its last parameter is the radius: set 0
        last = {"capsule": 7, "box": 6, "torus": 4}[kind]
        d = maximum(substitute(d, {f"p{last}": const(0.0)}), 0.0)
        d2 = _sq(d)
    R = param(_radius_column(kind))
    k = maximum(1.0 - d2 / _sq(R), 0.0)
    K = k * k * k
    return K * param(_radius_column(kind) + 1) if weighted else K


def _radius_column(kind):
    return {"sphere": 3, "capsule": 7, "box": 7, "torus": 5}[kind]


def _kernel_params(part: Part) -> np.ndarray:
    """Parameters of the blend kernel: the skeleton's, then R."""
    p = _distance_params(part)
    r = part.rows
    if part.kind == "sphere":
        return p
    if part.kind == "capsule":
        return p
    if part.kind == "box":
        # skeleton: the box of half sizes h - rounding, no offset; R = rounding
        return np.column_stack([p[:, :6], np.zeros(len(r)), r[:, 6]])
    return np.column_stack([r[:, :4], np.zeros(len(r)), r[:, 4]])


# ---------------------------------------------------------------------------
# Combinations
# ---------------------------------------------------------------------------

def _parts(parts) -> list:
    parts = [p for p in parts]
    if not parts or not all(isinstance(p, Part) for p in parts):
        raise TypeError("expected one or more parts (spheres(...), capsules(...), boxes(...), tori(...))")
    if sum(len(p) for p in parts) == 0:
        raise ValueError("no primitives given")
    return [p for p in parts if len(p)]


def _bbox(parts, margin):
    lo = np.min([p.extent()[0] for p in parts], 0)
    hi = np.max([p.extent()[1] for p in parts], 0)
    pad = margin + 0.02 * (hi - lo).max()
    return tuple(lo - pad), tuple(hi + pad)


def _f32(params) -> np.ndarray:
    """Parameters as float32 values (as Mitsuba's scene data): f is defined
    by these, and the kernel gathers each once, in float32, for both its
    float64 point values and its float32 intervals (exactly)."""
    return np.asarray(params, np.float64).astype(np.float32).astype(np.float64)


def _form(outer: Expr, op: str, groups, k: float, parts, margin: float) -> TableForm:
    tf = TableForm(outer, [Aggregate(op, groups, k)])
    tf.bbox = _bbox(parts, margin)
    return tf


def union(*parts) -> TableForm:
    """min over the primitives' signed distances."""
    parts = _parts(parts)
    groups = [make_group(_distance(p.kind), _f32(_distance_params(p))) for p in parts]
    return _form(var("A0"), "min", groups, 0.0, parts, 0.0)


def smooth_union(*parts, k: float) -> TableForm:
    """The polynomial smooth minimum of radius k, folded in order."""
    parts = _parts(parts)
    if not (np.isfinite(k) and k > 0):
        raise ValueError(f"smooth_union: k must be positive and finite, got {k}")
    groups = [make_group(_distance(p.kind), _f32(_distance_params(p))) for p in parts]
    # the fold lies up to smin_below below the union: the box reaches that far
    return _form(var("A0"), "smin", groups, float(k), parts,
                 float(smin_below(sum(len(p) for p in parts), float(k))))


def blend(*parts, threshold: float = 0.5) -> TableForm:
    """threshold - sum of w_i K(d_i / R_i) (K compactly supported)."""
    parts = _parts(parts)
    if not (np.isfinite(threshold) and threshold > 0):
        raise ValueError(f"blend: threshold must be positive, got {threshold}")
    groups = []
    for p in parts:
        prm = _kernel_params(p)
        if np.any(prm[:, _radius_column(p.kind)] <= 0):
            what = "boxes in a blend need rounding > 0 (their radius of influence)" \
                if p.kind == "box" else "radii must be positive"
            raise ValueError(f"blend: {what}")
        weighted = p.weights is not None
        if weighted:
            prm = np.column_stack([prm, p.weights])
        groups.append(make_group(_kernel(p.kind, weighted), _f32(prm)))
    radius = max(float(_kernel_params(p)[:, _radius_column(p.kind)].max()) for p in parts)
    return _form(named("threshold", float(threshold)) - var("A0"), "add", groups, 0.0, parts,
                 radius)


COMBINE = {"union": union, "smooth_union": smooth_union, "blend": blend}


def load(path: str, combine: str = "union", **kw) -> TableForm:
    """Primitives from a text file: one per line, ``kind v1 v2 ...`` with
    the columns of :data:`COLUMNS` (``box`` may leave out ``rounding``), an
    optional ``w=value`` blend weight at the end; ``#`` starts a comment.
    Errors name the file and line."""
    rows: dict = {}
    with open(path) as fh:
        for ln, line in enumerate(fh, 1):
            line = line.split("#", 1)[0].split()
            if not line:
                continue
            kind, vals = line[0], line[1:]
            w = 1.0
            if vals and vals[-1].startswith("w="):
                w, vals = vals[-1][2:], vals[:-1]
            if kind not in COLUMNS:
                raise ValueError(f"{path}:{ln}: unknown primitive {kind!r} "
                                 f"(one of {', '.join(COLUMNS)})")
            cols = COLUMNS[kind]
            if kind == "box" and len(vals) == len(cols) - 1:
                vals = vals + ["0"]
            if len(vals) != len(cols):
                raise ValueError(f"{path}:{ln}: {kind} takes {len(cols)} numbers "
                                 f"({' '.join(cols)}), got {len(vals)}")
            try:
                nums = [float(v) for v in vals] + [float(w)]
            except ValueError as err:
                raise ValueError(f"{path}:{ln}: {err}") from None
            rows.setdefault(kind, []).append(nums)
    if not rows:
        raise ValueError(f"{path}: no primitives")
    if combine not in COMBINE:
        raise ValueError(f"unknown combine {combine!r} (one of {', '.join(COMBINE)})")
    parts = []
    for kind, r in rows.items():
        a = np.array(r, np.float64)
        weights = a[:, -1] if np.any(a[:, -1] != 1.0) else None
        try:
            parts.append(Part(kind, a[:, :-1], weights))
        except ValueError as err:
            raise ValueError(f"{os.path.basename(path)}: {err}") from None
    return COMBINE[combine](*parts, **kw)


def save(path: str, *parts: Part):
    """Write parts as a primitives file (see :func:`load`)."""
    with open(path, "w") as fh:
        for p in parts:
            for i, r in enumerate(p.rows):
                w = f" w={p.weights[i]!r}" if p.weights is not None else ""
                fh.write(p.kind + " " + " ".join(repr(float(v)) for v in r) + w + "\n")
