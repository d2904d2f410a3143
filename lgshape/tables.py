"""Templates and tables: expressions of many similar parts, evaluated per region.

A modelled object is a combination of many parts of the same shape that
differ only in their constants: the N spheres of a union, the N kernels of a
blend. Such an f is held as a :class:`TableForm`:

    f = outer(x, y, z, A0, A1, ...),   Aj = combine over the rows of its groups

where each group is a *template* (an expression in x, y, z and parameters
p0, p1, ...) with a table of parameter rows, and the combine is ``min``,
``max``, ``add`` or ``smin`` (the polynomial smooth minimum with radius k,
folded over the rows in order). The outer expression is small (the template
structure only), so its compiled kernel does not depend on the number of
rows or on their values.

**Per-region rows.** For each pruning cell the build (:func:`build`) keeps
only the rows that can matter there, proven by interval bounds over the
(inflated) cell:

- ``min``: a row whose lower bound exceeds another row's upper bound never
  wins (``max`` alike);
- ``add``: a row proven *exactly* zero on the cell (compact support: a
  ``max(0, u)`` with u <= 0, a zero factor) adds nothing;
- ``smin``: a row whose lower bound is at least k above an earlier row's
  upper bound leaves the fold unchanged (the smooth minimum of a and b is
  exactly min(a, b) when |a - b| >= k).

On that cell, f equals the outer expression over the kept rows, exactly (no
approximation): the search there evaluates those rows only. The build runs
level by level over the octree on (cell, row) pairs, vectorised with numpy;
a child cell starts from its parent's kept rows.

:func:`find_tables` turns a plain expression into a TableForm where it holds
an n-ary min / max / sum of at least :data:`MIN_ROWS` operands of the same
structure (constants aside), so a union written out as text gets the same
treatment as one built with :mod:`lgshape.primitives`.
"""
from __future__ import annotations

import functools
import math
import re
from dataclasses import dataclass, field

import drjit as dr
import numpy as np

from . import interval as iv
from .arraymath import NUMPY
from .expr import evaluate, evaluate_interval, evaluate_with_error
from .expr import node as N
from .expr.diff import DX, DY, DZ, derivative
from .expr.node import Expr, const, maximum, minimum, named, topological, var
from .expr.quadratic import Quad, _norm_quotient, evaluate_quadratic, quad_env, quad_range
from .grid import row_slots

#: Operands of one structure needed before an n-ary node becomes a table.
MIN_ROWS = 16

#: The combines of an aggregate, with their identity (the value over no rows).
COMBINES = {"min": math.inf, "max": -math.inf, "add": 0.0, "smin": math.inf}

A, B = var("a"), var("b")


def combine_expr(op: str, k: float = 0.0) -> Expr:
    """The combine of an accumulator a with a new row's value b, as an
    expression (values, intervals, errors and derivatives then come from the
    evaluators and the op table)."""
    if op == "min":
        return minimum(A, B)
    if op == "max":
        return maximum(A, B)
    if op == "add":
        return A + B
    if op == "smin":        # k as named constants: any k keeps the structure
        h = maximum(0.0, named("k", k) - abs(A - B)) * named("k_inverse", 1.0 / k)
        return minimum(A, B) - named("k_quarter", 0.25 * k) * h * h
    raise ValueError(f"unknown combine {op!r} (one of {', '.join(COMBINES)})")


def smin_below(n, k: float):
    """How far the smooth minimum of radius k folded over n values can lie
    below their minimum: min((n - 1) k / 4, k). Each fold lowers by at most
    k / 4; and the whole fold by less than k: if the fold u so far is at
    least its operands' minimum m less k, a new value v >= m takes it to
    u - (k - (v - u))^2 / (4k), and v - u >= k - (u - (m - k)), so that stays
    above m - k; a new v < m gives at least v - x - (k - x)^2 / (4k) >= v - k
    with x = v - u in [0, k)."""
    n = np.asarray(n)
    return np.minimum(np.maximum(n - 1, 0) * (0.25 * k), k)


def param(q: int) -> Expr:
    return var(f"p{q}")


@functools.lru_cache(maxsize=256)
def point_slope(g: Expr) -> Expr:
    """g (a derivative) for point values at the singular points of the
    distances in it: each slope A / (c sqrt(U)) of a distance |v| =
    sqrt(v_1^2 + ... + v_k^2) (sqrt's derivative rule, as
    :func:`lgshape.expr.quadratic._norm_quotient` parses it) becomes
    A / (c sqrt(U) + (1 - step(U))): the same value where U > 0 (the added
    term is exactly 0), and A / 1 = 0 where U = 0 (every term of A has a
    factor v_i, all 0 there; where U underflows to 0, as tiny as they are)
    instead of 0 / 0. On a torus's axis, a
    capsule's segment, a sphere's centre, a box's inner box or a sharp
    box's faces, the slope of |v| along a ray is 0 where it exists (the ray
    along the axis: |v| is 0 all along it) and is else a kink between -|v'|
    and |v'|, whose middle is 0. So a row whose kernel is 0 there (a blend's
    torus on its axis: 0 times 0 / 0 was NaN) adds 0 to F's slope and to
    grad f, and the winning row of a union keeps its slope. These values
    steer Newton's steps and give normals; the proofs take the slope's
    bounds from the unchanged g (its forms bound the quotient by
    Cauchy-Schwarz where U's range reaches 0)."""
    out = {}
    for n in topological([g]):
        if n.op in ("const", "named", "var"):
            out[id(n)] = n
            continue
        args = [out[id(a)] for a in n.args]
        if n.op == "div" and _norm_quotient(n) is not None:
            num, den = args
            # the sqrt factor of the divisor (its other factors are constants)
            stack, root = [n.args[1]], None
            while stack:
                e = stack.pop()
                if e.op in ("mul", "neg"):
                    stack.extend(e.args)
                elif e.op == "sqrt":
                    root = e
            U = out[id(root.args[0])]
            out[id(n)] = N.div(num, N.add(den, N.sub(1.0, N.step(U))))
        else:
            out[id(n)] = n if all(a is b for a, b in zip(args, n.args)) else _rebuild(n, args)
    return out[id(g)]


@dataclass
class Group:
    """Rows of one template: ``template`` in x, y, z and p0..p{k-1};
    ``params`` (n, k) float64."""
    template: Expr
    params: np.ndarray

    def __post_init__(self):
        self.params = np.ascontiguousarray(np.asarray(self.params, np.float64).reshape(len(self.params), -1))
        if not np.all(np.isfinite(self.params)):
            raise ValueError("primitive parameters must be finite")

    @property
    def rows(self) -> int:
        return len(self.params)

    @property
    def width(self) -> int:
        return self.params.shape[1]

    def row_expr(self, i: int) -> Expr:
        return substitute(self.template, {f"p{q}": const(float(v))
                                          for q, v in enumerate(self.params[i])})


@dataclass
class Aggregate:
    """Aj = combine(op) over every row of every group, group after group."""
    op: str
    groups: list
    k: float = 0.0            # smin radius

    def __post_init__(self):
        if self.op not in COMBINES:
            raise ValueError(f"unknown combine {self.op!r} (one of {', '.join(COMBINES)})")
        if self.op == "smin" and not (math.isfinite(self.k) and self.k > 0):
            raise ValueError(f"smooth union needs a positive finite radius k, got {self.k}")

    @property
    def combine(self) -> Expr:
        return combine_expr(self.op, self.k)

    @property
    def rows(self) -> int:
        return sum(g.rows for g in self.groups)


@dataclass
class TableForm:
    """f = outer(x, y, z, A0, A1, ...) over aggregates (see the module notes)."""
    outer: Expr
    aggregates: list
    _expr: Expr | None = field(default=None, repr=False)

    @property
    def rows(self) -> int:
        return sum(a.rows for a in self.aggregates)

    @property
    def groups(self) -> list:
        """(aggregate index, group) for every group, in evaluation order."""
        return [(j, g) for j, a in enumerate(self.aggregates) for g in a.groups]

    def expr(self) -> Expr:
        """The whole f as one expression (the unpruned form: for oracles,
        comparisons and the numpy evaluators)."""
        if self._expr is None:
            sub = {}
            for j, a in enumerate(self.aggregates):
                terms = [g.row_expr(i) for g in a.groups for i in range(g.rows)]
                if a.op in ("min", "max", "add"):
                    sub[f"A{j}"] = _balanced(a.op, terms)
                else:
                    acc = terms[0]
                    comb = a.combine
                    for t in terms[1:]:
                        acc = substitute(comb, {"a": acc, "b": t})
                    sub[f"A{j}"] = acc
            self._expr = substitute(self.outer, sub)
        return self._expr

    def __repr__(self):
        parts = ", ".join(f"A{j} = {a.op} of {a.rows} rows in {len(a.groups)} template(s)"
                          for j, a in enumerate(self.aggregates))
        return f"TableForm({self.outer!r}; {parts})"


def _balanced(op, terms):
    if len(terms) == 1:
        return terms[0]
    if op == "add":
        while len(terms) > 1:
            nxt = [terms[i] + terms[i + 1] for i in range(0, len(terms) - 1, 2)]
            if len(terms) % 2:
                nxt.append(terms[-1])
            terms = nxt
        return terms[0]
    return (minimum if op == "min" else maximum)(*terms)


def substitute(e: Expr, values: dict) -> Expr:
    """e with variables replaced (name -> Expr), rebuilt with simplification."""
    out = {}
    for n in topological([e]):
        if n.op == "var":
            out[id(n)] = Expr.lift(values[n.param]) if n.param in values else n
        elif n.op in ("const", "named"):
            out[id(n)] = n
        else:
            args = [out[id(a)] for a in n.args]
            out[id(n)] = n if all(a is b for a, b in zip(args, n.args)) else _rebuild(n, args)
    return out[id(e)]


def _rebuild(n, args, op=None, param=None) -> Expr:
    """Node n (or op with param) over new arguments, with simplification."""
    op, param = (n.op, n.param) if n is not None else (op, param)
    if op == "pow":
        return N.power(args[0], param)
    if op in ("add", "sub", "mul", "div"):
        return getattr(N, op)(*args)
    if op == "neg":
        return N.neg(args[0])
    if op == "min":
        return N.minimum(*args)
    if op == "max":
        return N.maximum(*args)
    if op == "abs":
        return N.abs_(args[0])
    if op in ("step", "kink"):
        return getattr(N, op)(args[0])
    return N.unary(op)(args[0])


# ---------------------------------------------------------------------------
# Finding tables in a plain expression
# ---------------------------------------------------------------------------

def _flatten(node: Expr):
    """Operands of the n-ary min / max / sum rooted at node, as (sign, Expr)
    (sign -1 for subtracted terms of a sum). Iterative."""
    op = "add" if node.op == "sub" else node.op
    out, stack = [], [(1, node)]
    while stack:
        s, n = stack.pop()
        if op == "add" and n.op in ("add", "sub"):
            stack.append((-s if n.op == "sub" else s, n.args[1]))
            stack.append((s, n.args[0]))
        elif op != "add" and n.op == op:
            stack.append((s, n.args[1]))
            stack.append((s, n.args[0]))
        else:
            out.append((s, n))
    return out


def _structure(e: Expr):
    """(key, constants): e's DAG with its constants abstracted, as a
    hashable key, and the constants in the key's order."""
    nodes = topological([e])
    index, key, consts = {}, [], []
    for i, n in enumerate(nodes):
        index[id(n)] = i
        if n.op in ("const", "named"):     # named constants go to the table too
            key.append(("c",))
            consts.append(n.param if n.op == "const" else n.param[1])
        elif n.op == "var":
            key.append(("v", n.param))
        else:
            key.append((n.op, n.param, *(index[id(a)] for a in n.args)))
    return tuple(key), consts


def _template(key) -> tuple[Expr, int]:
    """The template expression of a structure key (constants -> p0, p1, ...)."""
    built, q = [], 0
    for item in key:
        if item[0] == "c":
            built.append(param(q))
            q += 1
        elif item[0] == "v":
            built.append(var(item[1]))
        else:
            op, prm, *args = item
            built.append(_rebuild(None, [built[a] for a in args], op, prm))
    return built[-1], q


def _fold_uniform(template: Expr, params: np.ndarray):
    """Parameters equal on every row become constants again (no gather for
    them in the kernel); the others are renumbered p0, p1, ..."""
    uniform = np.all(params == params[:1], axis=0)
    values, keep = {}, []
    for q in range(params.shape[1]):
        if uniform[q]:
            values[f"p{q}"] = const(float(params[0, q]))
        else:
            values[f"p{q}"] = param(len(keep))
            keep.append(q)
    return substitute(template, values), params[:, keep]


def make_group(template: Expr, params) -> Group:
    """A group with its uniform parameters folded into the template."""
    params = np.asarray(params, np.float64)
    t, p = _fold_uniform(template, params.reshape(len(params), -1))
    return Group(t, p)


def find_tables(f: Expr, min_rows: int = MIN_ROWS) -> TableForm | None:
    """A TableForm equal to f where f holds an n-ary min, max or sum with at
    least ``min_rows`` operands of one structure; None otherwise."""
    nodes = topological([f])
    parent_ops: dict = {}
    for n in nodes:
        for a in n.args:
            parent_ops.setdefault(id(a), set()).add("add" if n.op == "sub" else n.op)
    replaced, aggregates = {}, []
    for n in nodes:
        op = "add" if n.op == "sub" else n.op
        if op not in ("min", "max", "add"):
            continue
        if parent_ops.get(id(n), set()) == {op}:
            continue                      # inside a larger cluster of the same op
        operands = _flatten(n)
        if len(operands) < min_rows:
            continue
        by_key: dict = {}
        for s, e in operands:
            key, consts = _structure(e)
            by_key.setdefault((s, key), []).append(consts)
        tables = {k: v for k, v in by_key.items() if len(v) >= min_rows}
        if not tables:
            continue
        groups = []
        for (s, key), rows in tables.items():
            t, _ = _template(key)
            groups.append(make_group(t if s > 0 else -t, np.array(rows, np.float64)))
        rest = [(s, e) for s, e in operands if (s, _structure(e)[0]) not in tables]
        aggregates.append(Aggregate(op, groups))
        replaced[id(n)] = (len(aggregates) - 1, rest, op)
    if not aggregates:
        return None
    # Rebuild the outer expression with the aggregates as variables A0, A1...
    out = {}
    for n in nodes:
        if id(n) in replaced:
            j, rest, op = replaced[id(n)]
            acc = var(f"A{j}")
            for s, e in rest:
                term = out.get(id(e), e)
                acc = (acc + term if s > 0 else acc - term) if op == "add" else \
                    (minimum(acc, term) if op == "min" else maximum(acc, term))
            out[id(n)] = acc
        elif n.op in ("const", "named", "var"):
            out[id(n)] = n
        else:
            args = [out.get(id(a), a) for a in n.args]
            out[id(n)] = n if all(a is b for a, b in zip(args, n.args)) else _rebuild(n, args)
    return TableForm(out[id(f)], aggregates, _expr=f)


# ---------------------------------------------------------------------------
# Per-cell rows: interval rules (numpy float64, host)
# ---------------------------------------------------------------------------

#: Pairs per block of the host interval evaluation (blocks stay in cache).
BLOCK = 1 << 15


def row_intervals(group: Group, rows, lo, hi, zeros: bool = False):
    """Interval of the template over boxes [lo, hi] (P, 3) for rows (P,),
    and (with ``zeros``) where it is exactly zero on the box: (lo, hi, zero)."""
    if len(rows) > BLOCK:
        parts = [_row_intervals(group, rows[s:s + BLOCK], lo[s:s + BLOCK], hi[s:s + BLOCK], zeros)
                 for s in range(0, len(rows), BLOCK)]
        return tuple(None if p[0] is None else np.concatenate(p) for p in zip(*parts))
    return _row_intervals(group, rows, lo, hi, zeros)


def _row_intervals(group, rows, lo, hi, zeros):
    env = {v: iv.Interval(lo[:, i], hi[:, i]) for i, v in enumerate("xyz")}
    P = group.params[rows]
    for q in range(group.width):
        env[f"p{q}"] = P[:, q]
    with np.errstate(all="ignore"):
        if zeros:       # every node's interval, for the exact-zero proof
            nodes = topological([group.template])
            vals = evaluate_interval(nodes, env, NUMPY)
            zero = _exact_zero(nodes, vals, env, len(rows))
            r = vals[-1]
        else:
            r, zero = evaluate_interval(group.template, env, NUMPY), None
    rlo = np.broadcast_to(r.lo, len(rows)).astype(np.float64)
    rhi = np.broadcast_to(r.hi, len(rows)).astype(np.float64)
    # NaN bounds say nothing: the row may take any value.
    rlo = np.where(np.isnan(rlo), -np.inf, rlo)
    rhi = np.where(np.isnan(rhi), np.inf, rhi)
    # An empty interval (undefined on the whole box) is kept as unknown.
    empty = rlo > rhi
    rlo, rhi = np.where(empty, -np.inf, rlo), np.where(empty, np.inf, rhi)
    return rlo, rhi, zero


def _exact_zero(nodes, vals, env, P):
    """Per node, where its value is exactly 0 at every point of the box (a
    structural proof from the intervals of its arguments)."""
    z, ival = {}, {id(n): v for n, v in zip(nodes, vals)}
    for n in nodes:
        if n.op in ("const", "named"):
            z[id(n)] = np.full(P, (n.param if n.op == "const" else n.param[1]) == 0.0)
        elif n.op == "var":
            val = env.get(n.param)
            z[id(n)] = (np.broadcast_to(val == 0.0, P) if not isinstance(val, iv.Interval)
                        else np.zeros(P, bool))
        else:
            za = [z[id(a)] for a in n.args]
            ia = [ival[id(a)] if isinstance(ival[id(a)], iv.Interval)
                  else iv.Interval(ival[id(a)], ival[id(a)]) for a in n.args]
            finite = [np.isfinite(i.lo) & np.isfinite(i.hi) for i in ia]
            op = n.op
            if op == "max":
                r = (za[0] & (ia[1].hi <= 0)) | (za[1] & (ia[0].hi <= 0))
            elif op == "min":
                r = (za[0] & (ia[1].lo >= 0)) | (za[1] & (ia[0].lo >= 0))
            elif op == "mul":
                r = (za[0] & finite[1]) | (za[1] & finite[0])
            elif op in ("add", "sub"):
                r = za[0] & za[1]
            elif op == "div":
                r = za[0] & finite[1] & ((ia[1].lo > 0) | (ia[1].hi < 0))
            elif op == "pow":
                r = za[0] if n.param > 0 else np.zeros(P, bool)
            elif op in ("neg", "abs", "sqrt"):
                r = za[0]
            else:
                r = np.zeros(P, bool)
            z[id(n)] = np.broadcast_to(r, P)
    return z[id(nodes[-1])]



#: Relative inflation of cells for the row lists: twice the occupancy test's
#: (grid.INFLATE), since a search segment reaches its margin past the cell.
ROW_INFLATE = 2e-3

_CHILDREN = np.array([[i, j, k] for k in (0, 1) for j in (0, 1) for i in (0, 1)])


#: Row lists are kept per *row cell*, 2^ROW_UP fine cells on an edge (0: a
#: fine cell, 2: a brick of the pruning grid, at most), so that a search segment runs from the first
#: occupied fine cell to the row cell's exit, not one fine cell at a time.
ROW_UP = 1


@dataclass
class CellRows:
    """The build's result: occupied fine cells, the row cells (2^``up``
    fine cells on an edge, at level depth - up) that hold some, and, per
    group (in :attr:`TableForm.groups` order), the rows kept on each row
    cell as pairs (index into ``row_cells``, row), sorted by row cell then
    row."""
    cells: np.ndarray          # (n, 3) int64: occupied fine cells
    row_cells: np.ndarray      # (m, 3) int64: row cells, at level depth - up
    up: int                    # levels between the row cells and the fine cells
    pair_cell: list            # per group: (P,) int64
    pair_row: list             # per group: (P,) int64
    tested: int                # cells tested
    pairs_tested: int          # (cell, row) intervals evaluated


def _segments(cell):
    """Start of each run of equal values in a sorted array."""
    if len(cell) == 0:
        return np.zeros(0, np.int64)
    return np.flatnonzero(np.r_[True, cell[1:] != cell[:-1]])


def _seg_reduce(ufunc, cell, v, n, identity):
    out = np.full(n, identity, np.float64)
    s = _segments(cell)
    if len(s):
        out[cell[s]] = ufunc.reduceat(v, s)
    return out


def _seg_count(cell, n):
    return np.bincount(cell, minlength=n) if len(cell) else np.zeros(n, np.int64)


def _seg_exclusive_cummin(cell, v):
    """Per run of equal cells, the min of the values before each one."""
    out = np.concatenate([[np.inf], v[:-1]]) if len(v) else v.copy()
    if len(v):
        out[_segments(cell)] = np.inf
    same = cell
    step = 1
    while step < len(v):
        prev = np.concatenate([np.full(step, np.inf), out[:-step]])
        ok = np.concatenate([np.zeros(step, bool), same[step:] == same[:-step]])
        out = np.where(ok, np.minimum(out, prev), out)
        step *= 2
    return out


def _prune_aggregate(agg, ivals, ncells):
    """Keep masks (per group) and the aggregate's interval per cell."""
    if agg.op == "min":
        best_hi = np.full(ncells, np.inf)
        for c, lo, hi, _ in ivals:
            best_hi = np.minimum(best_hi, _seg_reduce(np.minimum, c, hi, ncells, np.inf))
    if agg.op == "max":
        best_lo = np.full(ncells, -np.inf)
        for c, lo, hi, _ in ivals:
            best_lo = np.maximum(best_lo, _seg_reduce(np.maximum, c, lo, ncells, -np.inf))
    keeps = []
    before = np.full(ncells, np.inf)          # smin: min upper bound of earlier groups
    for c, lo, hi, zero in ivals:
        if agg.op == "min":
            keep = lo <= best_hi[c]
        elif agg.op == "max":
            keep = hi >= best_lo[c]
        elif agg.op == "add":
            keep = ~zero
        else:
            prior = np.minimum(_seg_exclusive_cummin(c, hi), before[c])
            keep = ~(lo >= prior + agg.k)
            before = np.minimum(before, _seg_reduce(np.minimum, c, hi, ncells, np.inf))
        keeps.append(keep)
    # The aggregate's interval over each cell, from its kept rows.
    if agg.op in ("min", "smin", "max"):
        red = np.minimum if agg.op != "max" else np.maximum
        ident = np.inf if agg.op != "max" else -np.inf
        a_lo, a_hi = np.full(ncells, ident), np.full(ncells, ident)
        count = np.zeros(ncells, np.int64)
        for (c, lo, hi, _), keep in zip(ivals, keeps):
            a_lo = red(a_lo, _seg_reduce(red, c[keep], lo[keep], ncells, ident))
            a_hi = red(a_hi, _seg_reduce(red, c[keep], hi[keep], ncells, ident))
            count += _seg_count(c[keep], ncells)
        if agg.op == "smin":                  # each fold lowers by at most k / 4,
            # and the folds together by less than k (smin_below)
            a_lo = a_lo - smin_below(count, agg.k)
    else:
        a_lo, a_hi, mag = np.zeros(ncells), np.zeros(ncells), np.zeros(ncells)
        count = np.zeros(ncells, np.int64)
        for (c, lo, hi, _), keep in zip(ivals, keeps):
            a_lo += _seg_reduce(np.add, c[keep], lo[keep], ncells, 0.0)
            a_hi += _seg_reduce(np.add, c[keep], hi[keep], ncells, 0.0)
            mag += _seg_reduce(np.add, c[keep], np.maximum(np.abs(lo[keep]), np.abs(hi[keep])),
                               ncells, 0.0)
            count += _seg_count(c[keep], ncells)
        slack = (count + 2) * 2.0**-52 * mag + 2.0**-1020   # the sum's rounding
        a_lo, a_hi = a_lo - slack, a_hi + slack
    return keeps, a_lo, a_hi


def build(tf: TableForm, lo, hi, depth: int, up: int = ROW_UP) -> CellRows:
    """Occupied cells and the rows of each row cell, level by level (see the
    module notes): the row lists are those of level depth - up, the cells
    those of the last level."""
    if not 0 <= up <= 2:
        raise ValueError(f"up must be 0, 1 or 2 (row cells within a brick), got {up}")
    up = min(up, depth)
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    groups = tf.groups
    cells = np.zeros((1, 3), np.int64)
    pair_cell = [np.zeros(g.rows, np.int64) for _, g in groups]
    pair_row = [np.arange(g.rows, dtype=np.int64) for _, g in groups]
    tested = pairs_tested = 0
    for level in range(depth + 1):
        n = len(cells)
        size = (hi - lo) / 2 ** level
        clo = lo + cells * size - ROW_INFLATE * size
        chi = lo + (cells + 1) * size + ROW_INFLATE * size
        tested += n
        # Interval of every (cell, row) pair, then the aggregate rules.
        ivals = []
        for gi, (j, g) in enumerate(groups):
            c, r = pair_cell[gi], pair_row[gi]
            pairs_tested += len(c)
            zeros = tf.aggregates[j].op == "add"
            rlo, rhi, zero = row_intervals(g, r, clo[c], chi[c], zeros) if len(c) else \
                (np.zeros(0), np.zeros(0), np.zeros(0, bool))
            ivals.append((c, rlo, rhi, zero))
        env = {v: iv.Interval(clo[:, i], chi[:, i]) for i, v in enumerate("xyz")}
        start = 0
        for j, agg in enumerate(tf.aggregates):
            k = len(agg.groups)
            keeps, a_lo, a_hi = _prune_aggregate(agg, ivals[start:start + k], n)
            for gi in range(start, start + k):
                keep = keeps[gi - start]
                pair_cell[gi], pair_row[gi] = pair_cell[gi][keep], pair_row[gi][keep]
            env[f"A{j}"] = iv.Interval(a_lo, a_hi)
            start += k
        with np.errstate(all="ignore"):
            fi = evaluate_interval(tf.outer, env, NUMPY)
        flo = np.broadcast_to(fi.lo, n)
        fhi = np.broadcast_to(fi.hi, n)
        occupied = ~((flo > 0) | (fhi < 0))           # NaN bounds keep the cell
        rank = np.cumsum(occupied) - 1
        cells = cells[occupied]
        for gi in range(len(groups)):
            keep = occupied[pair_cell[gi]]
            pair_cell[gi], pair_row[gi] = rank[pair_cell[gi][keep]], pair_row[gi][keep]
        if level == depth - up:
            rows_at = (cells.copy(), [c.copy() for c in pair_cell], [r.copy() for r in pair_row])
        if level == depth:
            break
        cells = (2 * cells[:, None, :] + _CHILDREN[None]).reshape(-1, 3)
        for gi in range(len(groups)):
            c = (8 * pair_cell[gi][:, None] + np.arange(8)[None]).reshape(-1)
            r = np.repeat(pair_row[gi], 8)
            order = np.argsort(c, kind="stable")
            pair_cell[gi], pair_row[gi] = c[order], r[order]
    row_cells, pc, pr = rows_at
    if up:      # the row cells that hold an occupied fine cell
        used = np.unique(_code(cells >> up, 2 ** (depth - up)))
        keep = np.isin(_code(row_cells, 2 ** (depth - up)), used)
        rank = np.cumsum(keep) - 1
        row_cells = row_cells[keep]
        for gi in range(len(groups)):
            k = keep[pc[gi]]
            pc[gi], pr[gi] = rank[pc[gi][k]], pr[gi][k]
    return CellRows(cells, row_cells, up, pc, pr, tested, pairs_tested)


def _code(ijk, R):
    return (ijk[:, 2] * R + ijk[:, 1]) * R + ijk[:, 0]


# ---------------------------------------------------------------------------
# Numpy evaluation (host): f at points, in chunks of rows
# ---------------------------------------------------------------------------

def evaluate_points(tf: TableForm, p, chunk: int = 256) -> np.ndarray:
    """f at points p (n, 3), float64, over every row (the unpruned form,
    without building the whole expression)."""
    p = np.asarray(p, np.float64).reshape(-1, 3)
    env = {v: p[:, i, None] for i, v in enumerate("xyz")}
    out = dict((v, p[:, i]) for i, v in enumerate("xyz"))
    with np.errstate(all="ignore"):
        for j, agg in enumerate(tf.aggregates):
            acc = None
            for g in agg.groups:
                for s in range(0, g.rows, chunk):
                    e = dict(env)
                    for q in range(g.width):
                        e[f"p{q}"] = g.params[None, s:s + chunk, q]
                    v = np.broadcast_to(evaluate(g.template, e, NUMPY),
                                        (len(p), min(chunk, g.rows - s)))
                    if agg.op in ("min", "max", "add"):
                        red = {"min": np.min, "max": np.max, "add": np.sum}[agg.op](v, axis=1)
                        acc = red if acc is None else evaluate(agg.combine, {"a": acc, "b": red}, NUMPY)
                    else:
                        for col in range(v.shape[1]):
                            acc = v[:, col] if acc is None else \
                                evaluate(agg.combine, {"a": acc, "b": v[:, col]}, NUMPY)
            out[f"A{j}"] = acc
        return np.broadcast_to(evaluate(tf.outer, out, NUMPY), len(p)).astype(np.float64)


# ---------------------------------------------------------------------------
# Table-local coordinates: a template's offsets x - p folded about a centre
# ---------------------------------------------------------------------------

#: The local coordinate of each axis in a localized template.
LOCAL = {"x": "lx", "y": "ly", "z": "lz"}


def _offset_operands(n: Expr):
    """(axis, s_x, other, s_o) where n is s_x * axis + s_o * other with an
    axis variable x, y or z and a parameter or constant other; else None."""
    if n.op not in ("add", "sub"):
        return None
    a, b = n.args
    leaf = ("const", "var")
    if a.op == "var" and a.param in LOCAL and b.op in leaf and b.param not in LOCAL:
        return a.param, 1.0, b, (1.0 if n.op == "add" else -1.0)
    if b.op == "var" and b.param in LOCAL and a.op in leaf and a.param not in LOCAL:
        return b.param, (1.0 if n.op == "add" else -1.0), a, 1.0
    return None


def _offset_nodes(t: Expr):
    """(node, axis, s_x, other, s_o) for each offset node of t (see
    :func:`_offset_operands`)."""
    out = []
    for n in topological([t]):
        found = _offset_operands(n)
        if found is not None:
            out.append((n, *found))
    return out


def localize_template(t: Expr, ct, columns: bool = True):
    """t with its offsets rewritten about the table centre ct (x, y, z).

    Each node ``x - p``, ``x + p``, ``p - x`` (p a parameter or constant,
    x an axis) becomes ``lx - P``, ``lx + P``, ``P - lx`` with the local
    coordinate lx = x - ct[x] and P = p -/+ ct[x]: the same value, computed
    from small numbers, where x - p in float32 far from the origin loses the
    digits of a small part. Other uses of x stay global. A constant p gives
    a constant P where that is exact in float64; otherwise (and for a
    parameter) P is a new parameter p{width + i} (with ``columns``; without,
    the node stays global). Returns (template, offsets): per new parameter,
    (source column or constant, axis, s_x, s_o), P = s_o p + s_x ct[axis]."""
    width = 1 + max([int(n.param[1:]) for n in topological([t])
                     if n.op == "var" and re.fullmatch(r"p\d+", n.param)], default=-1)
    local = {id(n): f for n, *f in _offset_nodes(t)}
    made, offsets, out = {}, [], {}
    for n in topological([t]):
        if id(n) in local:
            axis, sx, other, so = local[id(n)]
            lx, c = var(LOCAL[axis]), float(ct["xyz".index(axis)])
            P = None
            if other.op == "const":
                v, e = _two_sum(so * other.param, sx * c)
                if e == 0.0:
                    P = const(float(v))
            if P is None and columns:
                src = int(other.param[1:]) if other.op == "var" else float(other.param)
                key = (other.op, src, axis, sx, so)
                if key not in made:
                    made[key] = param(width + len(offsets))
                    offsets.append((src, axis, sx, so))
                P = made[key]
            if P is not None:
                # s_x x + s_o p = s_x lx + (s_o p + s_x ct): the node's op kept
                out[id(n)] = N.add(lx, P) if sx > 0 else N.sub(P, lx)
                continue
        if n.op in ("const", "named", "var"):
            out[id(n)] = n
        else:
            args = [out[id(a)] for a in n.args]
            out[id(n)] = n if all(a is b for a, b in zip(args, n.args)) else _rebuild(n, args)
    return out[id(t)], offsets


def table_centre(tf: "TableForm", lo, hi) -> np.ndarray:
    """Per axis, the centre of the box [lo, hi] rounded to a multiple of a
    coarse power of two S: the largest one at most half the box's largest
    extent, and at least the largest float32 ulp of the offsets' parameters
    and constants. A float32 parameter p is then a multiple of ulp(p) as
    ct is, so p - ct is exact in float32 wherever |p - ct| is within about
    |p| (the box near p: Sterbenz's lemma), and a float64 constant K - ct
    exact in float64; the local coordinates stay within the box's size of 0
    (ct is within S / 2 of the centre). Near the origin ct is 0."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    c = 0.5 * (lo + hi)
    half = 0.5 * float((hi - lo).max())
    S = np.full(3, 2.0 ** math.floor(math.log2(half)) if half > 0 else 0.0)
    templates = [(g.template, g.params) for _, g in tf.groups] + [(tf.outer, None)]
    for t, params in templates:
        for _, axis, _, other, _ in _offset_nodes(t):
            if other.op == "const":
                big = abs(other.param)
            elif params is not None and len(params):
                big = float(np.abs(params[:, int(other.param[1:])]).max())
            else:
                continue
            i = "xyz".index(axis)
            S[i] = max(S[i], float(np.spacing(np.float32(big))))
    return np.where(S > 0, np.round(c / np.where(S > 0, S, 1.0)) * S, c)


def _two_sum(a, b):
    """(s, e) with s = fl(a + b) and a + b = s + e exactly (Knuth)."""
    s = a + b
    bb = s - a
    return s, (a - (s - bb)) + (b - bb)


# ---------------------------------------------------------------------------
# Device side (Dr.Jit): per-cell row ranges and the evaluations over them
# ---------------------------------------------------------------------------

@dataclass(init=False, eq=False)
class DeviceTables:
    """A TableForm's rows on one Dr.Jit backend, ordered by pruning cell.

    Per group: the parameters of the (cell, row) pairs, cell after cell
    (float64 for point values; float32 for intervals, as lower and upper
    roundings where a value is not a float32), and ``start`` with the pairs
    of cell slot s at [start[s], start[s + 1]). A cell's slot is its place in
    the brick map (brick * 64 + bit); slot ``n_slots`` holds every row (for
    points outside the occupied cells).

    The search works in coordinates u local to the box centre c. Each
    template's offsets ``x - p`` are rewritten about a table centre ct near
    c (:func:`localize_template`, :func:`table_centre`): ``lx - P`` with
    lx = u + (c - ct) and P = p - ct per row, computed on the host exactly
    or with its error bound carried. So x - p is formed from small numbers
    and a part 1e6 from the origin is solved to the same relative accuracy
    as one at the origin. Other uses of x take x = u + c. The centres are
    opaque values (their roundings in the error bounds and the intervals),
    not folded into the templates, so the compiled code depends on the
    templates only: another table of the same templates (other rows,
    values, box) reuses the compiled kernels.

    Its fields are its Dr.Jit arrays (a frozen function's inputs)."""
    centre64: list
    centre32: list
    local64: list
    local32: list
    local_err: list
    groups: list

    def __init__(self, tf: TableForm, rows: CellRows, grid, centre, Float):
        self.Float = Float
        self.Float64 = dr.float64_array_t(Float)
        UInt32 = dr.uint32_array_t(Float)
        slot_of_cell = row_slots(grid, rows.row_cells, rows.up)
        self.up = rows.up
        self.n_slots = int(len(grid.bricks) // 2) * (8 ** (2 - rows.up))
        c64 = np.asarray(centre, np.float64)
        self.centre64 = [dr.opaque(self.Float64, float(v)) for v in c64]
        self.centre32 = [_enclose32(Float, v) for v in c64]
        # the local coordinates lx = x - c_t of the localized templates
        ct = table_centre(tf, grid.lo, grid.hi)
        delta, e = _two_sum(c64, -ct)           # exact where ct is near c (Sterbenz)
        self.local64 = [dr.opaque(self.Float64, float(v)) for v in delta]
        self.local_err = [dr.opaque(self.Float64, abs(float(b))) if b != 0 else 0.0 for b in e]
        self.local32 = [_enclose32(Float, v, abs(float(b))) for v, b in zip(delta, e)]
        seeds = {"x": DX, "y": DY, "z": DZ, "lx": DX, "ly": DY, "lz": DZ}
        self.groups = []
        for gi, (j, g) in enumerate(tf.groups):
            slot = slot_of_cell[rows.pair_cell[gi]]
            order = np.lexsort((rows.pair_row[gi], slot))
            slot, prow = slot[order], rows.pair_row[gi][order]
            prow = np.concatenate([prow, np.arange(g.rows)])         # the all-rows slot
            start = np.searchsorted(slot, np.arange(self.n_slots + 1)).astype(np.int64)
            start = np.concatenate([start, [len(prow)]])
            t, offsets = localize_template(g.template, ct)
            P = g.params[prow]
            cols, bound = [P[:, q] for q in range(g.width)], [0.0] * g.width
            for src, axis, sx, so in offsets:
                p = np.full(len(prow), src) if isinstance(src, float) else P[:, src]
                s, e = _two_sum(so * p, sx * ct["xyz".index(axis)])
                cols.append(s)
                bound.append(float(np.abs(e).max(initial=0.0)))
            P = np.column_stack(cols) if cols else P
            width = P.shape[1]
            bound = np.array(bound)
            exact = bool(np.all(P.astype(np.float32).astype(np.float64) == P)) and not bound.any()
            # float32 enclosures of each parameter's exact value P +- bound
            lo64 = np.where(bound > 0, np.nextafter(P - bound, -np.inf), P)
            hi64 = np.where(bound > 0, np.nextafter(P + bound, np.inf), P)
            lo32, hi32 = _round_down32(lo64), _round_up32(hi64)
            g_t = derivative(t, seeds)
            self.groups.append(_DeviceGroup(
                aggregate=j, template=t, g=g_t, gp=point_slope(g_t),
                start=UInt32(start.astype(np.uint32)),
                # float32 values are gathered once, as float32, for both
                p64=None if exact else [self.Float64(np.ascontiguousarray(P[:, q]))
                                        for q in range(width)],
                p32=[(Float(np.ascontiguousarray(lo32[:, q])),
                      None if exact else Float(np.ascontiguousarray(hi32[:, q])))
                     for q in range(width)],
                err=[dr.opaque(self.Float64, float(b)) if b > 0 else None for b in bound],
                width=width))
        self.aggregates = tf.aggregates
        self.outer, _ = localize_template(tf.outer, ct, columns=False)
        gseeds = dict(seeds, **{f"A{j}": var(f"gA{j}") for j in range(len(tf.aggregates))})
        self.outer_g = derivative(self.outer, gseeds)
        self.outer_gp = point_slope(self.outer_g)
        self.combines = [(a.combine, derivative(a.combine, {"a": var("ga"), "b": var("gb")}))
                         for a in tf.aggregates]

    def _coordinates(self, env, err, m64):
        """env and err with the box-local x, y, z made global (x = u + c) and
        the table-local lx, ly, lz (lx = u + (c - c_t)), with their roundings."""
        env, err = dict(env), dict(err)
        for i, v in enumerate("xyz"):
            u, eu = env[v], err.get(v, 0.0)
            lv = LOCAL[v]
            env[lv] = u + self.local64[i]
            err[lv] = eu + m64.u * dr.abs(env[lv]) + self.local_err[i]
            env[v] = u + self.centre64[i]
            err[v] = eu + m64.u * dr.abs(env[v])
        return env, err

    # -- ranges ---------------------------------------------------------------
    def ranges(self, slot, active):
        """(start, end) per group for the cells of slot (UInt32), where active."""
        UInt32 = dr.uint32_array_t(self.Float)
        out = []
        for grp in self.groups:
            s = dr.gather(UInt32, grp.start, slot, active)
            e = dr.gather(UInt32, grp.start, slot + 1, active)
            out.append((s, dr.select(active, e, s)))
        return out

    def all_rows(self, n):
        # opaque: the slot count (the number of bricks) is data, not kernel code
        return self.ranges(dr.opaque(dr.uint32_array_t(self.Float), self.n_slots, n), True)

    # -- point values -----------------------------------------------------------
    def point(self, env, err, rng, m64, directions=None):
        """F with its error bound and dF/dt along each direction (dicts of dx,
        dy, dz; default: the one in env), over the rows of rng.
        Returns (F, eF, [g, ...])."""
        Float64 = self.Float64
        dirs = directions or [{k: env[k] for k in ("dx", "dy", "dz")}]
        env, err = self._coordinates(env, err, m64)
        nd = len(dirs)
        vals, errs, grads = {}, {}, [dict() for _ in dirs]
        for j, agg in enumerate(self.aggregates):
            comb, comb_g = self.combines[j]
            first = dr.full(dr.mask_t(Float64), True, dr.width(env["x"]))
            v = dr.zeros(Float64, dr.width(env["x"]))
            state = (v, Float64(v), *[Float64(v) for _ in range(nd)], first)
            for grp, (s, e) in zip(self.groups, rng):
                if grp.aggregate != j:
                    continue

                def body(i, v, ev, *rest, grp=grp, comb=comb, comb_g=comb_g):
                    gs, first = rest[:-1], rest[-1]
                    penv, perr = dict(env), dict(err)
                    for q in range(grp.width):
                        penv[f"p{q}"] = dr.gather(Float64, grp.p64[q], i) if grp.p64 else \
                            Float64(dr.gather(self.Float, grp.p32[q][0], i))
                        if grp.err[q] is not None:
                            perr[f"p{q}"] = grp.err[q]
                    tv, te = evaluate_with_error(grp.template, penv, perr, m64, safety=False)
                    tg = [evaluate(grp.gp, {**penv, **dd}, m64) for dd in dirs]
                    cv, ce = evaluate_with_error(comb, {"a": v, "b": tv}, {"a": ev, "b": te}, m64,
                                                 safety=False)
                    cg = [evaluate(comb_g, {"a": v, "b": tv, "ga": ga, "gb": gb}, m64)
                          for ga, gb in zip(gs, tg)]
                    v = dr.select(first, tv, cv)
                    ev = dr.select(first, te, ce)
                    gs = [dr.select(first, b_, c_) for b_, c_ in zip(tg, cg)]
                    return (i + 1, v, ev, *gs, dr.mask_t(Float64)(False) & first)

                out = dr.while_loop(state=(s, *state), cond=lambda i, *_, e=e: i < e,
                                    body=body, label="lgshape_rows")
                state = out[1:]
            v, ev, *gs = state[:-1]
            first = state[-1]
            ident = COMBINES[agg.op]
            vals[f"A{j}"] = dr.select(first, ident, v)
            errs[f"A{j}"] = dr.select(first, 0.0, ev)
            for k in range(nd):
                grads[k][f"gA{j}"] = dr.select(first, 0.0, gs[k])
        F, eF = evaluate_with_error(self.outer, {**env, **vals}, {**err, **errs}, m64)
        g = [evaluate(self.outer_gp, {**env, **vals, **dd, **gk}, m64) for dd, gk in zip(dirs, grads)]
        return F, eF, g

    # -- both at once ---------------------------------------------------------------
    def point_segment(self, env, err, rng, m64, e32, d32, lo, hi, m):
        """F with its error bound and g = dF/dt at one point (as
        :meth:`point`, along env's direction), and float32 bounds of g and F
        over the local segment e + [lo, hi] d, in one loop over the rows:
        each row's parameters are gathered once for both (where they are
        exact in float32; a gather costs about as much as a small
        evaluation). The bounds are the ranges of quadratic forms along the
        segment (:mod:`lgshape.expr.quadratic`), kept per aggregate across
        its rows. Returns (F, eF, g, (g_lo, g_hi, F_lo, F_hi))."""
        Float, Float64 = self.Float, self.Float64
        dd = {k: env[k] for k in ("dx", "dy", "dz")}
        env, err = self._coordinates(env, err, m64)
        seg, qenv0 = quad_env(m, e32, d32, lo, hi, self.centre32,
                              local={LOCAL[v]: self.local32[i] for i, v in enumerate("xyz")})
        n = dr.width(lo)
        vals, errs, grads, avals, agrads = {}, {}, {}, {}, {}
        for j, agg in enumerate(self.aggregates):
            comb, comb_g = self.combines[j]
            z64, z32 = dr.zeros(Float64, n), dr.zeros(Float, n)
            state = (z64, Float64(z64), Float64(z64)) + tuple(Float(z32) for _ in range(8)) \
                + (dr.full(dr.mask_t(Float), True, n),)
            for grp, (s, e) in zip(self.groups, rng):
                if grp.aggregate != j:
                    continue

                def body(i, v, ev, gv, *rest, grp=grp, comb=comb, comb_g=comb_g):
                    qv, qg, first = Quad(*rest[0:4]), Quad(*rest[4:8]), rest[8]
                    penv, perr, qenv = dict(env), dict(err), dict(qenv0)
                    for q in range(grp.width):
                        plo, phi = grp.p32[q]
                        a = dr.gather(Float, plo, i)
                        penv[f"p{q}"] = dr.gather(Float64, grp.p64[q], i) if grp.p64 \
                            else Float64(a)
                        qenv[f"p{q}"] = a if phi is None else \
                            iv.Interval(a, dr.gather(Float, phi, i))
                        if grp.err[q] is not None:
                            perr[f"p{q}"] = grp.err[q]
                    # the point
                    tv, te = evaluate_with_error(grp.template, penv, perr, m64, safety=False)
                    tg = evaluate(grp.gp, {**penv, **dd}, m64)
                    cv, ce = evaluate_with_error(comb, {"a": v, "b": tv}, {"a": ev, "b": te},
                                                 m64, safety=False)
                    cg = evaluate(comb_g, {"a": v, "b": tv, "ga": gv, "gb": tg}, m64)
                    # the segment
                    tq, tgq = evaluate_quadratic([grp.template, grp.g], qenv, seg)
                    cq, cgq = evaluate_quadratic([comb, comb_g], {
                        "a": qv, "b": tq, "ga": qg, "gb": tgq}, seg)
                    f64 = dr.mask_t(Float64)(first)
                    return (i + 1, dr.select(f64, tv, cv), dr.select(f64, te, ce),
                            dr.select(f64, tg, cg),
                            *(dr.select(first, x, y) for x, y in zip(
                                (tq.c0, tq.c1, tq.c2, tq.R, tgq.c0, tgq.c1, tgq.c2, tgq.R),
                                (cq.c0, cq.c1, cq.c2, cq.R, cgq.c0, cgq.c1, cgq.c2, cgq.R))),
                            dr.mask_t(Float)(False) & first)

                out = dr.while_loop(state=(s, *state), cond=lambda i, *_, e=e: i < e,
                                    body=body, label="lgshape_rows_both")
                state = out[1:]
            v, ev, gv, *rest = state
            first = rest[8]
            ident = COMBINES[agg.op]
            f64 = dr.mask_t(Float64)(first)
            vals[f"A{j}"] = dr.select(f64, ident, v)
            errs[f"A{j}"] = dr.select(f64, 0.0, ev)
            grads[f"gA{j}"] = dr.select(f64, 0.0, gv)
            # an aggregate without rows is its identity (maybe infinite):
            # the outer expression's intervals take it exactly
            ra, rg = quad_range(seg, Quad(*rest[0:4])), quad_range(seg, Quad(*rest[4:8]))
            avals[f"A{j}"] = iv.Interval(dr.select(first, ident, ra.lo),
                                         dr.select(first, ident, ra.hi))
            agrads[f"gA{j}"] = iv.Interval(dr.select(first, 0.0, rg.lo),
                                           dr.select(first, 0.0, rg.hi))
        F, eF = evaluate_with_error(self.outer, {**env, **vals}, {**err, **errs}, m64)
        g = evaluate(self.outer_gp, {**env, **vals, **dd, **grads}, m64)
        ienv = {v: quad_range(seg, qenv0[v]) for v in ("x", "y", "z", *LOCAL.values())}
        ienv.update({k: qenv0[k] for k in ("dx", "dy", "dz")})
        Fi, gi = evaluate_interval([self.outer, self.outer_g], {**ienv, **avals, **agrads}, m)
        return F, eF, g, (gi.lo, gi.hi, Fi.lo, Fi.hi)


@dataclass
class _DeviceGroup:
    aggregate: int
    template: Expr
    g: Expr              # the template's slope (its forms and intervals)
    gp: Expr             # the same for point values (point_slope: 0 / 0 is 0)
    start: object
    p64: list
    p32: list
    err: list            # error bounds of the float64 parameters (None: exact)
    width: int


def _round_down32(v):
    v32 = v.astype(np.float32)
    return np.where(v32.astype(np.float64) > v, np.nextafter(v32, np.float32(-np.inf)), v32)


def _round_up32(v):
    v32 = v.astype(np.float32)
    return np.where(v32.astype(np.float64) < v, np.nextafter(v32, np.float32(np.inf)), v32)


def _enclose32(Float, v: float, e: float = 0.0):
    """(lo, hi): opaque float32 values enclosing v +- e (float64)."""
    lo, hi = np.array([v]), np.array([v])
    if e > 0:
        lo, hi = np.nextafter(lo - e, -np.inf), np.nextafter(hi + e, np.inf)
    return (dr.opaque(Float, float(_round_down32(lo)[0])), dr.opaque(Float, float(_round_up32(hi)[0])))
