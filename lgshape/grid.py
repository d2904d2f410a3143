"""Space pruning (the seed's octree) and its traversal along rays.

Build (host, numpy float64): start from the bounding box and subdivide it as
an octree down to ``depth``; at each level discard the cells where f provably
keeps one sign. Tests (each sound, so a cell is discarded if any holds):

- ``"global"``: the seed's |f(c)| > L d with one L for the whole box;
- ``"local"`` (default): |f(c)| > L_cell d with L_cell from the interval
  gradient over the cell, or 0 outside the interval of f over the cell.

Cells are tested slightly inflated (``INFLATE`` of their size), so a surface
point within rounding of a face keeps both neighbours. The depth bound is
what ends the subdivision when a cell corner lies exactly on the surface.

Storage is a brick map: a dense top grid of (R/4)^3 brick indices and, per
occupied brick only, 4^3 = 64 occupancy bits (two uint32). The bricks grow
with the surface, not with the volume.

Traversal (Dr.Jit, any backend): an Amanatides-Woo DDA over the fine cells
that jumps over empty bricks in one step (:func:`dda_next_occupied`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .arraymath import NUMPY
from .bounds import box_env, lipschitz
from .expr import evaluate, evaluate_interval

BRICK = 4            # fine cells per brick edge (4^3 = 64 bits)
INFLATE = 1e-3       # relative inflation of cells in the pruning tests


@dataclass
class PruningGrid:
    lo: np.ndarray            # (3,) bounding box
    hi: np.ndarray
    depth: int                # fine resolution R = 2 ** depth per axis
    top: np.ndarray           # uint32 (R/4)^3: brick index + 1, 0 = empty
    bricks: np.ndarray        # uint32 (n_bricks * 2,) occupancy bits
    cells: np.ndarray         # int32 (n, 3) occupied fine cells (for tests)
    tested: int               # number of cell tests made during the build

    @property
    def resolution(self) -> int:
        return 2 ** self.depth

    @property
    def cell_size(self) -> np.ndarray:
        return (self.hi - self.lo) / self.resolution

    @property
    def nbytes(self) -> int:
        return self.top.nbytes + self.bricks.nbytes

    def occupied(self, ijk) -> np.ndarray:
        """Occupancy of fine cells (n, 3) read back through the brick map."""
        ijk = np.asarray(ijk, dtype=np.int64)
        b, bit = _brick_of(ijk, self.resolution)
        idx = self.top[b].astype(np.int64)
        word = np.where(idx > 0, self.bricks[np.maximum(2 * (idx - 1), 0) + (bit >> 5)], 0)
        return (idx > 0) & (((word >> (bit & 31)) & 1) == 1)


def _brick_of(ijk, R):
    nb = R // BRICK
    bx, by, bz = (ijk[..., i] // BRICK for i in range(3))
    b = (bz * nb + by) * nb + bx
    lx, ly, lz = (ijk[..., i] % BRICK for i in range(3))
    bit = lx + BRICK * (ly + BRICK * lz)
    return b, bit


def may_contain_surface(f, lo, hi, mode="local", L=None) -> np.ndarray:
    """For boxes [lo, hi] (n, 3): False where f provably has one sign."""
    c, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    d = np.sqrt((half ** 2).sum(-1))      # centre to farthest corner
    fc = evaluate(f, {v: c[:, i] for i, v in enumerate("xyz")}, NUMPY)
    if mode == "global":
        return ~(np.abs(fc) > L * d)
    if mode != "local":
        raise ValueError(f"unknown pruning mode {mode!r} (use 'local' or 'global')")
    with np.errstate(all="ignore"):
        Lc = lipschitz(f, lo, hi)
        fi = evaluate_interval(f, box_env(lo, hi), NUMPY)
    keep = ~(np.abs(fc) > Lc * d) & (fi.lo <= 0) & (fi.hi >= 0)
    return keep | np.isnan(fc)


def build(f, lo, hi, depth: int = 6, mode: str = "local", L: float | None = None) -> PruningGrid:
    """Prune the box [lo, hi] down to 2**depth cells per axis."""
    if depth < 2 or depth > 10:
        raise ValueError(f"depth must be between 2 and 10, got {depth}")
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    if mode == "global" and L is None:
        L = float(lipschitz(f, lo[None], hi[None])[0])
    cells = np.zeros((1, 3), np.int64)
    tested = 0
    for level in range(depth + 1):
        size = (hi - lo) / 2 ** level
        clo = lo + cells * size - INFLATE * size
        chi = lo + (cells + 1) * size + INFLATE * size
        tested = tested + len(cells)
        cells = cells[may_contain_surface(f, clo, chi, mode, L)]
        if level < depth:
            offsets = np.array([[i, j, k] for k in (0, 1) for j in (0, 1) for i in (0, 1)])
            cells = (2 * cells[:, None, :] + offsets[None]).reshape(-1, 3)
    return _brick_map(lo, hi, depth, cells, tested)


def _brick_map(lo, hi, depth, cells, tested) -> PruningGrid:
    R = 2 ** depth
    nb = R // BRICK
    b, bit = _brick_of(cells, R)
    used, slot = np.unique(b, return_inverse=True)
    top = np.zeros(nb ** 3, np.uint32)
    top[used] = np.arange(1, len(used) + 1, dtype=np.uint32)
    words = np.zeros(2 * len(used), np.uint64)
    np.bitwise_or.at(words, 2 * slot + (bit >> 5), np.uint64(1) << (bit & 31).astype(np.uint64))
    return PruningGrid(lo, hi, depth, top, words.astype(np.uint32),
                       cells.astype(np.int32), tested)


# ---------------------------------------------------------------------------
# Traversal (Dr.Jit)
# ---------------------------------------------------------------------------

class DeviceGrid:
    """The brick map as Dr.Jit arrays of one backend, with opaque scalars so
    that another grid of the same depth reuses the compiled kernels."""

    def __init__(self, grid: PruningGrid, Float):
        import drjit as dr
        UInt32 = dr.uint32_array_t(Float)
        self.R = grid.resolution
        self.top = UInt32(grid.top)
        self.bricks = UInt32(grid.bricks) if len(grid.bricks) else dr.zeros(UInt32, 2)
        self.lo = [dr.opaque(Float, float(v)) for v in grid.lo]
        self.cell = [dr.opaque(Float, float(v)) for v in grid.cell_size]


class DDA:
    """Per-ray traversal state: current cell, crossing times, steps."""

    def __init__(self, g: DeviceGrid, o, d, t):
        import drjit as dr
        Float = type(t)
        Int32 = dr.int32_array_t(Float)
        self.i, self.t_next, self.dt, self.step = [], [], [], []
        for a in range(3):
            p = (o[a] + t * d[a] - g.lo[a]) / g.cell[a]
            i = dr.clip(Int32(dr.floor(p)), 0, g.R - 1)
            pos = d[a] > 0
            bound = g.lo[a] + Float(i + dr.select(pos, 1, 0)) * g.cell[a]
            flat = d[a] == 0
            self.i.append(i)
            self.step.append(dr.select(pos, Int32(1), Int32(-1)))
            self.t_next.append(dr.select(flat, dr.inf, (bound - o[a]) / d[a]))
            self.dt.append(dr.select(flat, dr.inf, g.cell[a] / dr.abs(d[a])))

    # Loop state for dr.while_loop: a flat tuple of arrays.
    def state(self):
        return (*self.i, *self.t_next, *self.dt, *self.step)

    @classmethod
    def from_state(cls, s):
        obj = cls.__new__(cls)
        obj.i, obj.t_next, obj.dt, obj.step = list(s[0:3]), list(s[3:6]), list(s[6:9]), list(s[9:12])
        return obj


def dda_next_occupied(g: DeviceGrid, dda: DDA, t_cur, t_end, active):
    """Advance ``dda`` from the cell it is in to the first occupied cell
    (inclusive), jumping over empty bricks. Returns (found, t_enter, t_exit,
    dda after that cell, t after that cell). Lanes that leave the grid or pass
    t_end return found = False."""
    import drjit as dr
    Float = type(t_cur)
    Int32 = dr.int32_array_t(Float)
    UInt32 = dr.uint32_array_t(Float)
    Bool = dr.mask_t(Float)
    B = BRICK
    nb = g.R // B

    def cond(found, t_enter, t_exit, t, active, *s):
        return active

    def body(found, t_enter, t_exit, t, active, *s):
        q = DDA.from_state(s)
        ix, iy, iz = q.i
        inside = (ix >= 0) & (ix < g.R) & (iy >= 0) & (iy < g.R) & (iz >= 0) & (iz < g.R) & (t <= t_end)
        active = active & inside
        b = UInt32(((iz >> 2) * nb + (iy >> 2)) * nb + (ix >> 2))
        slot = dr.gather(UInt32, g.top, b, active)
        has_brick = active & (slot > 0)
        bit = UInt32((ix & 3) + B * ((iy & 3) + B * (iz & 3)))
        word = dr.gather(UInt32, g.bricks, 2 * (slot - 1) + (bit >> 5), has_brick)
        occupied = has_brick & (((word >> (bit & 31)) & 1) == 1)

        # Next boundary crossing of this cell (one fine step).
        t_exit_cell = dr.minimum(dr.minimum(q.t_next[0], q.t_next[1]), q.t_next[2])
        # Exit of the whole (empty) brick: cells left to its far face per axis.
        n = [dr.select(q.step[a] > 0, B - (q.i[a] & 3), (q.i[a] & 3) + 1) for a in range(3)]
        t_face = [dr.select(dr.isfinite(q.dt[a]), q.t_next[a] + Float(n[a] - 1) * q.dt[a], dr.inf)
                  for a in range(3)]
        t_brick = dr.minimum(dr.minimum(t_face[0], t_face[1]), t_face[2])
        skip = active & ~has_brick
        t_stop = dr.select(skip, t_brick, t_exit_cell)
        new_i, new_tn = [], []
        for a in range(3):
            crosses = q.t_next[a] <= t_stop
            k_one = dr.select(crosses, 1, 0)
            frac = dr.floor((t_stop - q.t_next[a]) / q.dt[a]) + 1
            k_many = dr.select(~crosses, 0,
                               dr.select(t_face[a] <= t_stop, n[a],
                                         dr.clip(Int32(dr.select(dr.isfinite(frac), frac, 1)), 1, n[a] - 1)))
            k = Int32(dr.select(skip, k_many, k_one))
            k = dr.select(active, k, 0)
            new_i.append(q.i[a] + q.step[a] * k)
            new_tn.append(dr.select(k > 0, q.t_next[a] + Float(k) * q.dt[a], q.t_next[a]))
        found = Bool(occupied)
        t_enter = dr.select(occupied, t, t_enter)
        t_exit = dr.select(occupied, t_exit_cell, t_exit)
        t = dr.select(active, t_stop, t)
        q.i, q.t_next = new_i, new_tn
        active = active & ~occupied
        return (found, t_enter, t_exit, t, active, *q.state())

    n = dr.width(t_cur)
    out = dr.while_loop(
        state=(dr.zeros(Bool, n), dr.zeros(Float, n), dr.zeros(Float, n), Float(t_cur),
               Bool(active), *dda.state()),
        cond=cond, body=body, label="lgshape_dda")
    found, t_enter, t_exit, t, _, *s = out
    return found, t_enter, t_exit, DDA.from_state(s), t
