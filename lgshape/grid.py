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

Traversal (Dr.Jit, any backend): a DDA over the fine cells that crosses
empty space in large steps, using each empty cell's distance to the nearest
occupied one (a dense table of four bits a cell, up to DENSE_MAX_DEPTH; for
rays that enter the grid from outside, the distance ahead in the octant of
their direction), or each empty brick's (:func:`next_occupied`).
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import numpy as np

from .arraymath import NUMPY
from .bounds import box_env, lipschitz
from .expr import evaluate, evaluate_interval

BRICK = 4            # fine cells per brick edge (4^3 = 64 bits)
INFLATE = 1e-3       # relative inflation of cells in the pruning tests (> the walk's nudge)


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
    # A NaN centre value makes the Lipschitz test inconclusive (kept); the
    # interval over the cell's defined part still decides.
    return ~(np.abs(fc) > Lc * d) & (fi.lo <= 0) & (fi.hi >= 0)


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
    return brick_map(lo, hi, depth, cells, tested)


def brick_map(lo, hi, depth, cells, tested) -> PruningGrid:
    """The brick map of the occupied fine cells (n, 3)."""
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

@dataclass(init=False, eq=False)
class DeviceGrid:
    """The pruning grid as Dr.Jit arrays of one backend, with opaque scalars
    so that another grid of the same depth reuses the compiled kernels.

    - The brick map: the top grid holds brick index + 1 for occupied bricks
      and -k for empty ones, where k is the chessboard distance (in bricks,
      at most MAX_SKIP) to the nearest occupied brick: the (2k - 1)^3 bricks
      around an empty one are all empty, so a ray crosses them in one step.
    - Up to :data:`DENSE_MAX_DEPTH`, also a dense table of every fine cell,
      four bits each (:func:`dense_table`), which the walk reads with one
      gather per step (on the CPUs measured, a gather costs about as much
      as a whole evaluation of a small f) and whose rings let it skip empty
      space in any direction. Finer grids walk the brick map.
    - Up to :data:`OCTANT_MAX_DEPTH`, after it in the same array, eight
      more tables, one per octant of directions (:func:`octant_rings`),
      for the rays that enter the grid from outside (:class:`Walker`).

    Its fields are its Dr.Jit arrays (a frozen function's inputs)."""
    top: object
    bricks: object
    cell: list
    table: object

    def __init__(self, grid: PruningGrid, Float):
        Int32 = dr.int32_array_t(Float)
        UInt32 = dr.uint32_array_t(Float)
        self.R = grid.resolution
        self.top = Int32(_with_distances(grid.top, grid.resolution // BRICK))
        self.bricks = UInt32(grid.bricks) if len(grid.bricks) else dr.zeros(UInt32, 2)
        self.cell = [dr.opaque(Float, float(v)) for v in grid.cell_size]
        self.dense = grid.depth <= DENSE_MAX_DEPTH
        self.octants = grid.depth <= OCTANT_MAX_DEPTH
        self.table_words = self.R ** 3 // 8          # words of one table
        self.table = UInt32(walk_table(grid)) if self.dense else None


#: The dense walk table is built up to this depth (256^3 cells, 8 MB; 1 MB
#: at depth 7). Measured against the brick map, 512^2 camera rays: union of
#: 1000 spheres (depth 7) 85 -> 69-75 ms, of 10000 (depth 8) 160-167 ->
#: 132-138 ms; blend of 10000 blobs (depth 8) 190-210 -> 174-177 ms. With 4
#: bytes a cell (the slot, and a Euclidean distance bound) the table was
#: 1.5x slower than the brick map at depth 8.
DENSE_MAX_DEPTH = 8
#: The octant tables are built up to this depth (8 tables of 1 MB at
#: depth 7; 64 MB at depth 8 would not stay in the caches). Measured,
#: 512^2 camera rays, in one process: torus, Barth, gyroid 1.15x, 1.12x,
#: 1.08x faster than the cube table alone. Incoherent rays (random origins
#: in the box) were 1.13x slower with them (their steps spread over all
#: eight tables, 8 MB, past the 1 MB L2 cache): rays that start inside the
#: grid walk the cube table.
OCTANT_MAX_DEPTH = 7
#: The largest ring count of the dense table (four bits a cell: 1 + k <=
#: 15). Measured against a byte a cell (rings up to 254), 512^2 camera and
#: 262144 incoherent rays, interleaved in one process: camera within 2%,
#: incoherent 7-9% faster (the table is half the size in the caches; the
#: longer skips were rarely taken), the scale models at depth 8 5% faster.
MAX_RINGS = 14


def row_slots(grid: PruningGrid, row_cells, up: int) -> np.ndarray:
    """The slot of row cells (n, 3; 2^up fine cells on an edge, up <= 2)
    where a table form keeps their rows: brick * 8^(2 - up) + the row
    cell's place in its brick (:func:`row_slot` on the device); -1 for a
    row cell in an empty brick."""
    sub = BRICK >> up
    rc = np.asarray(row_cells, np.int64)
    b, _ = _brick_of(rc << up, grid.resolution)
    loc = rc % sub
    place = loc[:, 0] + sub * (loc[:, 1] + sub * loc[:, 2])
    v = grid.top[b].astype(np.int64)
    return np.where(v > 0, (v - 1) * sub ** 3 + place, -1)


def row_slot(g, i, up: int, active):
    """Device side of :func:`row_slots`: (slot, brick occupied) of the row
    cell holding fine cell i (three Int32); one gather (the top entry)."""
    v = dr.gather(dr.int32_array_t(type(i[0])), g.top,
                  dr.uint32_array_t(type(i[0]))(_brick_index(i, g.R)), active)
    return _row_place(v, i, up), active & (v > 0)


def _row_place(v, i, up: int):
    """The slot of fine cell i's row cell in the brick of top entry v."""
    UInt32 = dr.uint32_array_t(type(i[0]))
    sub = BRICK >> up
    place = [(a >> up) & (sub - 1) for a in i]
    return UInt32(v - 1) * sub ** 3 + UInt32(place[0] + sub * (place[1] + sub * place[2]))


def _brick_index(i, R: int):
    """The brick of fine cell i (three integer arrays, numpy or Dr.Jit) in
    the top grid: (K nb + J) nb + I with I = i >> 2 per axis."""
    nb = R // BRICK
    return ((i[2] >> 2) * nb + (i[1] >> 2)) * nb + (i[0] >> 2)


def _occupancy(grid: PruningGrid) -> np.ndarray:
    """The occupied fine cells as a dense bool array [k, j, i]."""
    R = grid.resolution
    cells = grid.cells.astype(np.int64)
    occ = np.zeros((R, R, R), bool)
    occ[cells[:, 2], cells[:, 1], cells[:, 0]] = True
    return occ


def dense_rings(grid: PruningGrid, octants=None) -> np.ndarray:
    """A value per fine cell (uint8), [k, j, i]: 0 for an occupied cell,
    1 + k for an empty one, where the cells i - k .. i + k on every axis
    are all empty (the chessboard distance transform to the occupied cells,
    less one), at most MAX_RINGS. From :func:`octant_rings` where given
    (the nearest occupied cell lies in some octant: the least of the eight),
    else scipy's transform."""
    if octants is not None:
        return octants.min(axis=0)
    from scipy import ndimage
    occ = _occupancy(grid)
    if occ.any():
        k = ndimage.distance_transform_cdt(~occ, metric="chessboard") - 1
    else:
        k = np.full(occ.shape, MAX_RINGS)
    return np.where(occ, 0, 1 + np.clip(k, 0, MAX_RINGS)).astype(np.uint8)


def octant_rings(grid: PruningGrid) -> np.ndarray:
    """(8, R, R, R) uint8, [o, k, j, i]: 0 for an occupied cell; for an
    empty one, 1 + k where the box of cells from i to i + k s_a on each
    axis a is empty, s the octant o of directions (bit a of o set: s_a =
    -1), at most MAX_RINGS. That is the chessboard distance to the nearest
    occupied cell in that octant (cells past the grid are empty). A ray
    going that way crosses the box, from any point of cell i, in one step:
    it is at least the cube of :func:`dense_rings`, far more where the
    occupied cells lie behind or beside the ray."""
    occ = _occupancy(grid)
    cap = MAX_RINGS + 1
    out = np.empty((8,) + occ.shape, np.uint8)
    # each octant's distance is separable (:func:`_ahead`): the passes along
    # x serve four octants each, those along y two
    for sx in (0, 1):
        ax = _ahead(np.where(occ, 0, cap).astype(np.uint8), 2, sx, cap, occ)
        for sy in (0, 1):
            axy = _ahead(ax, 1, sy, cap)
            for sz in (0, 1):
                out[sx | sy << 1 | sz << 2] = _ahead(axy, 0, sz, cap)
    return out


def _ahead(v: np.ndarray, axis: int, back: int, cap: int, occ=None) -> np.ndarray:
    """One separable pass of :func:`octant_rings` along ``axis``, forward
    (``back`` = 0: towards higher indices) or backward: the least over
    s = 0, 1, ... of max(s, v at s cells ahead), capped; with ``occ``, the
    first pass: the distance to the next occupied cell on the line."""
    R = v.shape[axis]
    out = v.copy()

    def ahead(s):        # the cells s ahead of the cells [0, R - s) (or back)
        src, dst = [slice(None)] * 3, [slice(None)] * 3
        if back:
            src[axis], dst[axis] = slice(0, R - s), slice(s, R)
        else:
            src[axis], dst[axis] = slice(s, R), slice(0, R - s)
        return tuple(src), tuple(dst)
    for s in range(1, min(cap, R)):
        src, dst = ahead(s)
        if occ is not None:
            np.minimum(out[dst], np.where(occ[src], s, cap).astype(np.uint8), out=out[dst])
        else:
            np.minimum(out[dst], np.maximum(v[src], np.uint8(s)), out=out[dst])
    return out


def _pack(rings: np.ndarray) -> np.ndarray:
    """Cell values [k, j, i] (0-15) in bricks of 4^3 cells, 32 bytes each
    (half a cache line: the cells near a ray's path, and near its
    neighbours', share lines), four bits a cell, eight cells to a uint32
    (the first in the low bits): see :func:`dense_index`."""
    nb = rings.shape[0] // BRICK
    b = rings.reshape(nb, BRICK, nb, BRICK, nb, BRICK)   # [K, k, J, j, I, i]
    b = b.transpose(0, 2, 4, 1, 3, 5)                      # [K, J, I, k, j, i]
    b = np.ascontiguousarray(b).reshape(-1)
    return (b[0::2] | (b[1::2] << 4)).view(np.uint32).copy()


def dense_table(grid: PruningGrid) -> np.ndarray:
    """:func:`dense_rings`, packed (:func:`_pack`)."""
    return _pack(dense_rings(grid))


def walk_table(grid: PruningGrid) -> np.ndarray:
    """The walk's tables in one array, R^3 / 8 words each: the cube table
    (:func:`dense_table`), then, up to :data:`OCTANT_MAX_DEPTH`, the eight
    octant tables (:func:`octant_rings`) in the order of their octants."""
    if grid.depth > OCTANT_MAX_DEPTH:
        return dense_table(grid)
    octants = octant_rings(grid)
    return np.concatenate([_pack(dense_rings(grid, octants))] + [_pack(r) for r in octants])


def dense_index(i, R: int):
    """The place c of fine cell i (three integer arrays, numpy or Dr.Jit)
    in :func:`dense_table` (word c >> 3, bits 4 (c & 7) up):
    ((K nb + J) nb + I) 64 + (k 4 + j) 4 + i, with (I, i) = divmod(i, 4)
    per axis."""
    return _brick_index(i, R) * 64 + (((i[2] & 3) << 4) | ((i[1] & 3) << 2) | (i[0] & 3))


MAX_SKIP = 8


def _with_distances(top: np.ndarray, nb: int) -> np.ndarray:
    """Top grid with -(chessboard distance to the nearest occupied brick) in
    empty bricks (capped at MAX_SKIP)."""
    occ = (top > 0).reshape(nb, nb, nb)
    dist = np.full(occ.shape, MAX_SKIP, np.int32)
    dist[occ] = 0
    reach = occ
    for k in range(1, MAX_SKIP):
        grown = _dilate26(reach)
        dist[grown & ~reach] = k
        reach = grown
    out = top.astype(np.int64).copy()
    empty = out == 0
    out[empty] = -dist.reshape(-1)[empty]
    return out.astype(np.int32)


def _dilate26(m: np.ndarray) -> np.ndarray:
    out = m.copy()
    for axis in range(3):
        shifted = np.zeros_like(out)
        sl_a = [slice(None)] * 3
        sl_b = [slice(None)] * 3
        sl_a[axis], sl_b[axis] = slice(1, None), slice(None, -1)
        shifted[tuple(sl_a)] |= out[tuple(sl_b)]
        shifted[tuple(sl_b)] |= out[tuple(sl_a)]
        out = out | shifted
    return out


def clip_to_box(o, d, lo, hi, t_min, t_max):
    """[t_start, t_end] of o + t d inside the box [lo, hi] and [t_min, t_max]
    (Dr.Jit arrays or lists of them, any precision; t_start > t_end where the
    ray misses)."""
    Float = type(o[0])
    t0, t1 = Float(-dr.inf), Float(dr.inf)
    for a in range(3):
        inv = 1.0 / d[a]
        ta, tb = (lo[a] - o[a]) * inv, (hi[a] - o[a]) * inv
        flat = d[a] == 0
        inside = (o[a] >= lo[a]) & (o[a] <= hi[a])
        t0 = dr.select(flat, dr.select(inside, t0, dr.inf), dr.maximum(t0, dr.minimum(ta, tb)))
        t1 = dr.select(flat, dr.select(inside, t1, -dr.inf), dr.minimum(t1, dr.maximum(ta, tb)))
    return dr.maximum(t0, Float(t_min)), dr.minimum(t1, Float(t_max))


def nudge_cells(R: int) -> float:
    """The positional nudge of the walk, in cells: 8 float32 ulps of R."""
    return 8.0 * R * 2.0**-24


def next_occupied(g: DeviceGrid, o, d, t, t_end, active):
    """From parameter t along o + t d, find the first occupied fine cell.

    ``o`` is the ray's origin relative to the grid's lower corner (the
    caller moves it to the box entry, so t stays small and float32 resolves
    the cells). A stateless DDA: each step locates the cell at t and moves t
    to the exit of that cell, or of the cube of empty bricks around it.
    Returns (found, t_enter, t_exit, stuck, slot) of that cell (``slot``:
    0; a table form's walker gives the cell's row cell, see
    :meth:`Walker.next`); lanes that pass t_end return found = False.

    Locating is nudged forward in *position*: each coordinate moves by
    ``NUDGE`` cells in the direction of travel, so a point on a face (within
    rounding of it) is located in the cell the ray enters, even where the
    face's t is uncertain (a ray nearly parallel to the face). That is sound
    because cells are pruned inflated by ``INFLATE`` (> NUDGE): a ray point
    within NUDGE of an empty cell has no surface. The walk is bounded: a line
    crosses at most 3 R cells, so a lane still walking after 4 R + 16 steps
    returns stuck = True (the caller counts it as capped). Where the nudged
    point lies past the grid's last face on an axis (the ray leaves through
    it within rounding), that face is ignored and the walk goes on through
    the boundary cells along it, so no cell the ray grazes is skipped."""
    return Walker(g, o, d, t_end).next(t, active)


class Walker:
    """The DDA of :func:`next_occupied` for one set of rays, with the
    per-ray constants computed once (a search calls :meth:`next` once per
    cell, inside its own loop)."""

    def __init__(self, g: DeviceGrid, o, d, t_end, rows_up: int | None = None, entering=None):
        """``entering`` (a mask, optional): the rays that enter the grid
        from outside (cameras, mostly: coherent rays). Through the dense
        table, they read the octant table of their direction, whose boxes
        reach further ahead (:func:`octant_rings`); the others read the
        cube table, eight times smaller in the caches."""
        self.g, self.d, self.t_end, self.up = g, d, t_end, rows_up
        R = g.R
        cell_min = dr.minimum(dr.minimum(g.cell[0], g.cell[1]), g.cell[2])
        dlen = dr.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        self.t_nudge = 1e-7 * cell_min / dr.select(dlen > 0, dlen, 1.0)  # fallback progress
        self.shift = [dr.select(d[a] > 0, nudge_cells(R),
                                dr.select(d[a] < 0, -nudge_cells(R), 0.0)) for a in range(3)]
        self.max_steps = 4 * R + 16
        # quotients once per ray, so that a step's chain of dependent
        # operations is short: the position in cells is fma(t, d / cell,
        # o / cell + shift), a face's t fma(face, cell / d, -o / d) (their
        # rounding, a few ulps of a position, stays far below the nudge)
        # (a direction 0 on an axis: cell_t = inf, and the faces it meets
        # are those ahead of a positive direction, all >= 1 cell: their t
        # is inf, and _exit ignores that axis without a test)
        inv_cell = [1.0 / g.cell[a] for a in range(3)]
        inv_d = [dr.select(d[a] == 0, 0.0, 1.0 / d[a]) for a in range(3)]
        self.d_cells = [d[a] * inv_cell[a] for a in range(3)]
        self.o_cells = [o[a] * inv_cell[a] + self.shift[a] for a in range(3)]
        self.cell_t = [dr.select(d[a] == 0, dr.inf, g.cell[a] * inv_d[a]) for a in range(3)]
        self.o_t = [-o[a] * inv_d[a] for a in range(3)]
        # -1 on the axes the ray goes down, else 0: the face ahead of a box
        # i - k .. i + k is i + 1 + (k ^ back) (i + k + 1 going up, i - k
        # going down)
        Int32 = dr.int32_array_t(type(d[0]))
        self.back = [dr.select(d[a] < 0, Int32(-1), 0) for a in range(3)]
        self.base = None       # the word where the ray's table starts
        if g.dense and g.octants and entering is not None:
            UInt32 = dr.uint32_array_t(type(d[0]))
            octant = (dr.select(d[0] < 0, UInt32(1), 0) | dr.select(d[1] < 0, UInt32(2), 0)
                      | dr.select(d[2] < 0, UInt32(4), 0))
            self.base = dr.select(entering, (octant + 1) * g.table_words, 0)

    def _cell(self, t):
        """The fine cell i of the ray at t (three Int32, located with the
        nudge) and, per axis, whether t lies past the grid's last face in
        the direction of travel (within rounding of it: the walk goes on in
        the boundary cells along that face)."""
        Int32 = dr.int32_array_t(type(t))
        R, d = self.g.R, self.d
        i, out = [], []
        for a in range(3):
            p = dr.fma(t, self.d_cells[a], self.o_cells[a])
            # truncation is the floor where it matters: p < 0 clips to 0
            i.append(dr.clip(Int32(p), 0, R - 1))
            out.append(((p >= R) & (d[a] > 0)) | ((p < 0) & (d[a] < 0)))
        return i, out

    def step(self, t, active):
        """One step of the DDA from t on the lanes ``active``: (hit, t_out,
        slot, inside). ``inside``: t had not passed t_end; ``hit``: the cell
        at t is occupied (its slot in the brick map; 0 through the dense
        table, see :meth:`next`); ``t_out``: the exit of that cell, or of
        the cube of empty cells or bricks around it."""
        g = self.g
        Float = type(t)
        UInt32 = dr.uint32_array_t(Float)
        B = BRICK
        inside = dr.mask_t(Float)(active) & (t <= self.t_end)
        i, out = self._cell(t)
        if g.dense:
            return self._dense_step(t, i, out, inside)
        v, brick, bit, hit = _cell_lookup(g, i, inside)
        # Exit of the cell (occupied brick) or of the empty cube of bricks.
        k = dr.select(brick, 0, dr.maximum(-v, 1))
        lo_c = [dr.select(brick, i[a], ((i[a] >> 2) - (k - 1)) * B) for a in range(3)]
        hi_c = [dr.select(brick, i[a] + 1, ((i[a] >> 2) + k) * B) for a in range(3)]
        return hit, self._exit(t, lo_c, hi_c, out), UInt32(v - 1) * 64 + bit, inside

    def _exit(self, t, lo_c, hi_c, out):
        """Where the ray at t leaves the box of cells [lo_c, hi_c) (three
        Int32 each; faces marked ``out`` ignored), past t by the nudge:
        rounding must never stall a ray."""
        return self._exit_faces(t, [dr.select(self.d[a] < 0, lo_c[a], hi_c[a]) for a in range(3)],
                                out)

    def _exit_faces(self, t, face, out):
        """:meth:`_exit` from the faces ahead of the ray (three Int32; >= 1
        on an axis where the direction is 0)."""
        Float = type(t)
        t_out = Float(dr.inf)
        for a in range(3):
            t_a = dr.fma(Float(face[a]), self.cell_t[a], self.o_t[a])
            t_out = _min(t_out, dr.select(out[a], dr.inf, t_a))
        return _max(t_out, t + _max(self.t_nudge, dr.abs(t) * 2.0**-22))

    def _dense_step(self, t, i, out, inside):
        """The step through the dense table: one gather. From an empty cell
        with k empty rings around it (:func:`dense_rings`), t moves on to
        where the ray leaves the cube of cells i - k .. i + k (through an
        octant table, the box from i to i + k ahead: :func:`octant_rings`).
        The slot of an occupied cell is not read here (see :meth:`next`)."""
        g = self.g
        Float = type(t)
        UInt32 = dr.uint32_array_t(Float)
        R = g.R
        c = UInt32(dense_index(i, R))           # (eight cells a word)
        word = c >> 3 if self.base is None else self.base + (c >> 3)
        w = dr.gather(UInt32, g.table, word, inside)
        b = type(i[0])((w >> ((c & 7) << 2)) & 15)
        hit = inside & (b == 0)
        # the exit of the cube of cells i - k .. i + k (k = b - 1; an
        # occupied cell's own exit: k = 0); of an octant table's box, the
        # same: the ray leaves a box through its faces ahead, which the
        # cube and the box of the ray's octant share
        k = dr.maximum(b - 1, 0)
        t_out = self._exit_faces(t, [a + 1 + (k ^ m) for a, m in zip(i, self.back)], out)
        return hit, t_out, dr.zeros(UInt32, dr.width(t)), inside

    def next(self, t, active):
        """(found, t_enter, t_exit, stuck, slot), see :func:`next_occupied`.
        For a walker of a table form (``rows_up``): ``slot`` is the found
        cell's row cell (:func:`row_slot`), and ``t_exit`` the exit of that
        row cell, the end of the segment its rows hold for."""
        Float = type(t)
        Int32 = dr.int32_array_t(Float)
        UInt32 = dr.uint32_array_t(Float)
        Bool = dr.mask_t(Float)
        max_steps = self.max_steps

        def body(t, active, found, t_enter, t_exit, steps):
            hit, t_out, _, inside = self.step(t, active)
            t_enter = dr.select(hit, t, t_enter)
            t_exit = dr.select(hit, t_out, t_exit)
            t = dr.select(inside & ~hit, t_out, t)
            steps = steps + 1
            return (t, inside & ~hit & (steps < max_steps), found | hit, t_enter, t_exit, steps)

        n = dr.width(t)
        t_in, walking, found, t_enter, t_exit, steps = dr.while_loop(
            state=(Float(t), Bool(active), dr.zeros(Bool, n), dr.zeros(Float, n),
                   dr.zeros(Float, n), dr.zeros(Int32, n)),
            cond=lambda t, active, *_: active, body=body, label="lgshape_dda")
        stuck = ~found & (steps >= max_steps) & (t_in <= self.t_end)
        slot = dr.zeros(UInt32, n)
        if self.up is not None:
            # the row cell of the cell at t_enter (located as in step()),
            # and where the ray leaves it
            i, out = self._cell(t_enter)
            up = self.up
            slot, _ = row_slot(self.g, i, up, found)
            t_row = self._exit(t_enter, [(a >> up) << up for a in i],
                               [((a >> up) + 1) << up for a in i], out)
            t_exit = dr.select(found, dr.maximum(t_exit, t_row), t_exit)
        return found, dr.select(found, t_enter, t_in), t_exit, stuck, slot


def _min(a, b):
    """min(a, b) where a is never NaN: b where it is surely smaller (a NaN b,
    from a near-zero direction's overflowed quotients, is ignored, as
    dr.minimum ignores it). One compare and select, one instruction on
    x86, where dr.minimum's NaN rule takes a few more."""
    return dr.select(b < a, b, a)


def _max(a, b):
    """max(a, b) where a is never NaN (see :func:`_min`)."""
    return dr.select(b > a, b, a)


def slot_at(g: DeviceGrid, p, up: int):
    """(slot, occupied) of the row cell (:func:`row_slot`) of the fine cell
    holding point p (grid-relative coordinates, a list of three Dr.Jit
    arrays); ``occupied``: that fine cell is occupied."""
    Float = type(p[0])
    Int32 = dr.int32_array_t(Float)
    R = g.R
    fl = [dr.floor(p[a] / g.cell[a]) for a in range(3)]
    inside = (fl[0] >= 0) & (fl[1] >= 0) & (fl[2] >= 0) & (fl[0] < R) & (fl[1] < R) & (fl[2] < R)
    i = [dr.clip(Int32(v), 0, R - 1) for v in fl]
    v, _, _, occupied = _cell_lookup(g, i, inside)
    return dr.select(occupied, _row_place(v, i, up), 0), occupied


def _cell_lookup(g: DeviceGrid, i, active):
    """The brick map at fine cell i (three Int32): (top entry v, occupied
    brick, bit of the cell in its brick, occupied cell)."""
    Int32 = dr.int32_array_t(type(i[0]))
    UInt32 = dr.uint32_array_t(type(i[0]))
    v = dr.gather(Int32, g.top, UInt32(_brick_index(i, g.R)), active)
    brick = active & (v > 0)
    bit = UInt32((i[0] & 3) + BRICK * ((i[1] & 3) + BRICK * (i[2] & 3)))
    word = dr.gather(UInt32, g.bricks, UInt32(2 * (v - 1)) + (bit >> 5), brick)
    return v, brick, bit, brick & (((word >> (bit & 31)) & 1) == 1)
