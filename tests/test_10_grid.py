"""The pruning grid: conservative, sparse, bounded.

Oracle: brute-force sampling in float64. Surface points are found as sign
changes of f along many random segments (bisected to 1e-12); every such point
must lie in an occupied cell (or within the cell inflation of one). Memory is
checked against the dense alternative."""
import numpy as np
import pytest
from conftest import JIT_AD, SURFACE_NAMES

from lgshape import grid as G
from lgshape.expr import evaluate
from lgshape.reference import first_sign_change
from lgshape.surfaces import LIBRARY


def surface_points(spec, rng, n=4000):
    lo, hi = np.asarray(spec.bbox[0]), np.asarray(spec.bbox[1])
    o = lo + (hi - lo) * rng.uniform(0, 1, (n, 3))
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)

    def F(X, Y, Z):
        return evaluate(spec.expr, {"x": X, "y": Y, "z": Z})
    t = first_sign_change(F, o, d, np.zeros(n), np.full(n, 0.5), steps=512)
    p = o + np.where(np.isfinite(t), t, 0)[:, None] * d
    inside = np.all((p >= lo) & (p <= hi), axis=1) & np.isfinite(t)
    return p[inside]


@pytest.mark.parametrize("mode", ["local", "global"])
@pytest.mark.parametrize("name", SURFACE_NAMES)
def test01_every_surface_point_is_in_an_occupied_cell(name, mode, rng):
    spec = LIBRARY[name]()
    g = G.build(spec.expr, *spec.bbox, depth=6, mode=mode)
    p = surface_points(spec, rng)
    assert len(p) > 200
    ijk = np.clip(np.floor((p - g.lo) / g.cell_size).astype(int), 0, g.resolution - 1)
    occ = g.occupied(ijk)
    # A point within rounding of a face may belong to the neighbour: check
    # the cells of the slightly moved point too.
    frac = (p - g.lo) / g.cell_size - ijk
    near_face = np.any((frac < 1e-6) | (frac > 1 - 1e-6), axis=1)
    assert np.all(occ | near_face), f"{(~occ & ~near_face).sum()} surface points in discarded cells"


def test02_local_pruning_keeps_fewer_cells_than_global():
    """The seed's global-L test keeps a superset of what local bounds need."""
    for name in ("tangle", "chmutov6", "torus"):
        spec = LIBRARY[name]()
        loc = G.build(spec.expr, *spec.bbox, depth=6, mode="local")
        glo = G.build(spec.expr, *spec.bbox, depth=6, mode="global")
        assert len(loc.cells) < len(glo.cells)


@pytest.mark.parametrize("name", SURFACE_NAMES)
def test03_sparse_memory(name):
    spec = LIBRARY[name]()
    g = G.build(spec.expr, *spec.bbox, depth=7)
    dense_bits = (2 ** 7) ** 3 // 8
    assert g.nbytes < 64 * 2**20                    # the budget
    assert g.nbytes < dense_bits                    # smaller than a dense bit grid
    # brick map round trip: exactly the occupied cells read back
    assert g.occupied(g.cells).all()
    assert g.nbytes == g.top.nbytes + 8 * (len(np.unique(g.top)) - 1)


def test04_depth_bounds_termination_on_exact_vertices():
    """A surface through grid vertices (x = 0.25 and a sphere of radius 0.5 in
    [-1, 1]^3) ends at the depth bound: the seed's non-termination case."""
    from lgshape import parse
    for text in ("x - 0.25", "x^2 + y^2 + z^2 - 0.25"):
        g = G.build(parse(text), (-1, -1, -1), (1, 1, 1), depth=6)
        assert 0 < len(g.cells) < 64**3


def test05_bad_depth():
    with pytest.raises(ValueError, match="depth"):
        G.build(LIBRARY["sphere"]().expr, (-1,) * 3, (1,) * 3, depth=11)


@pytest.mark.parametrize("name,depth", [("torus", 5), ("tangle", 6), ("sphere", 6)])
def test06_dense_table_rings(name, depth, rng):
    """The walk's dense table: a value per cell, 0 for the occupied cells,
    1 + k for an empty one (k at most MAX_RINGS = 14), in bricks of 4^3
    cells, four bits each, packed eight to a uint32. Oracle: brute force
    over all occupied cells: an empty cell's chessboard distance (in cells)
    to the nearest occupied cell is exactly k + 1 (so the cube of cells
    i - k .. i + k is empty and the next ring is not)."""
    spec = LIBRARY[name]()
    g = G.build(spec.expr, *spec.bbox, depth=depth)
    R = g.resolution
    rings = G.dense_rings(g)
    packed = G.dense_table(g)
    assert packed.dtype == np.uint32 and len(packed) * 8 == R ** 3
    ijk = rng.integers(0, R, (500, 3))
    c = G.dense_index([ijk[:, 0], ijk[:, 1], ijk[:, 2]], R)
    assert np.array_equal((packed[c >> 3] >> ((c & 7) * 4)) & 15,
                          rings[ijk[:, 2], ijk[:, 1], ijk[:, 0]])
    assert np.array_equal(np.sort(G.dense_index(np.indices((R, R, R)).reshape(3, -1), R)),
                          np.arange(R ** 3))                 # one byte per cell
    c = g.cells.astype(int)
    occ = np.zeros((R, R, R), bool)
    occ[c[:, 2], c[:, 1], c[:, 0]] = True
    assert np.array_equal(rings == 0, occ)
    empty = np.argwhere(rings > 0)[:, ::-1]                    # (i, j, k)
    pick = empty[rng.choice(len(empty), size=min(400, len(empty)), replace=False)]
    k = rings[pick[:, 2], pick[:, 1], pick[:, 0]].astype(int) - 1
    cheb = np.abs(c[None, :, :] - pick[:, None, :]).max(-1).min(1)
    assert np.array_equal(k + 1, np.minimum(cheb, G.MAX_RINGS + 1))
    assert (k >= 2).any()                       # the rings skip empty space


@pytest.mark.parametrize("name,depth", [("torus", 5), ("tangle", 6), ("chmutov6", 5)])
def test06b_octant_tables(name, depth, rng):
    """The eight octant tables (for the rays that enter the grid from
    outside): per octant of directions s, 0 for the occupied cells, else
    1 + k where the box of cells i .. i + k s is empty, k at most
    MAX_RINGS. Oracle: brute force over all occupied cells: the chessboard
    distance to the nearest occupied cell in that octant is exactly k + 1
    (capped). The cube table is their least value (scipy's transform is
    the other oracle), and the walk's array holds the nine tables in
    order."""
    spec = LIBRARY[name]()
    g = G.build(spec.expr, *spec.bbox, depth=depth)
    R = g.resolution
    octants = G.octant_rings(g)
    assert octants.shape == (8, R, R, R)
    assert np.array_equal(G.dense_rings(g, octants), G.dense_rings(g))
    c = g.cells.astype(int)
    for o in range(8):
        s = np.array([-1 if o >> a & 1 else 1 for a in range(3)])
        pick = rng.integers(0, R, (300, 3))                    # (i, j, k)
        ahead = (c[None, :, :] - pick[:, None, :]) * s         # per axis, >= 0 ahead
        dist = np.where((ahead >= 0).all(-1), ahead.max(-1), 10**6).min(1)
        assert np.array_equal(octants[o][pick[:, 2], pick[:, 1], pick[:, 0]],
                              np.minimum(dist, G.MAX_RINGS + 1))
    assert (octants.max(0) > G.dense_rings(g)).any()      # longer steps than the cube's
    table = G.walk_table(g)
    words = R ** 3 // 8
    assert len(table) == 9 * words
    ijk = rng.integers(0, R, (500, 3))
    cidx = G.dense_index([ijk[:, 0], ijk[:, 1], ijk[:, 2]], R)
    for part, rings in enumerate([G.dense_rings(g)] + list(octants)):
        w = table[part * words + (cidx >> 3)]
        assert np.array_equal((w >> ((cidx & 7) * 4)) & 15, rings[ijk[:, 2], ijk[:, 1], ijk[:, 0]])


@pytest.mark.parametrize("dense,octants", [(True, False), (True, True), (False, False)])
def test07_walk_visits_every_cell_a_line_crosses(dense, octants, rng, monkeypatch):
    """The walk (through the dense table, its octant tables, or the brick
    map used above DENSE_MAX_DEPTH) returns, in order, every occupied cell
    a ray crosses. Oracle: the cells under 8000 points per ray spaced along
    it (float64): every point in an occupied cell lies in a returned
    segment, and the segments are disjoint, in order, and one cell long at
    most. A few rays run along an axis (direction 0 on the others)."""
    import drjit as dr
    Float = JIT_AD.Float
    spec = LIBRARY["torus"]()
    g = G.build(spec.expr, *spec.bbox, depth=6)
    if not dense:
        monkeypatch.setattr(G, "DENSE_MAX_DEPTH", 5)
    dev = G.DeviceGrid(g, Float)
    assert dev.dense == dense
    lo, hi = np.asarray(g.lo), np.asarray(g.hi)
    n = 32
    o = lo + (hi - lo) * rng.uniform(0, 1, (n, 3))
    d = rng.normal(size=(n, 3))
    d[:3] = np.eye(3) * np.sign(d[:3])                  # along an axis, either way
    d[3, 0] = 0.0                                       # flat on one axis
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    # from each origin to the box's exit
    with np.errstate(divide="ignore"):
        t_exit = np.min(np.maximum((lo - o) / d, (hi - o) / d), axis=1)
    occupied = {tuple(v) for v in g.cells.tolist()}
    W = G.Walker(dev, [Float(o[:, a] - lo[a]) for a in range(3)],
                 [Float(d[:, a]) for a in range(3)], Float(t_exit),
                 entering=dr.full(dr.mask_t(Float), True, n) if octants else None)
    assert (W.base is not None) == octants
    t = dr.zeros(Float, n)
    active = dr.full(dr.mask_t(Float), True, n)
    segments = [[] for _ in range(n)]
    for _ in range(20 * g.resolution):
        found, ta, tb, stuck, slot = W.next(t, active)
        f, a_, b_ = (np.asarray(v) for v in (found, ta, tb))
        for r in np.flatnonzero(f):
            segments[r].append((float(a_[r]), float(b_[r])))
        assert not np.asarray(stuck).any()
        active = active & found
        t = dr.select(found, tb, t)
        if not dr.any(active):
            break
    s = np.linspace(0, 1, 8000)
    cell_t = float(g.cell_size.min())           # a cell, in t (unit directions)
    slack = 1e-5 * cell_t                       # the walk's nudge and rounding
    for r in range(n):
        seg = np.array(segments[r]).reshape(-1, 2)
        assert np.all(seg[:, 0] <= seg[:, 1]) and np.all(seg[1:, 0] >= seg[:-1, 1] - slack)
        assert np.all(seg[:, 1] - seg[:, 0] <= np.sqrt(3) * g.cell_size.max() + slack)
        ts = s * t_exit[r]
        ijk = np.clip(np.floor((o[r] + ts[:, None] * d[r] - lo) / g.cell_size).astype(int),
                      0, g.resolution - 1)
        inside_occ = np.array([c in occupied for c in map(tuple, ijk)])
        covered = ((ts[:, None] >= seg[None, :, 0] - slack)
                   & (ts[:, None] <= seg[None, :, 1] + slack)).any(1)
        assert np.all(covered[inside_occ]), (r, ts[inside_occ & ~covered][:5], seg)


def test08_default_depth_by_expression_size():
    """A small expression is pruned at DEFAULT_DEPTH (7), one of over
    DEEP_MAX_NODES nodes at 6 (its build at 7 costs seconds), a given depth
    is kept."""
    import lgshape
    from lgshape import trace as T
    small = lgshape.Surface(LIBRARY["torus"]())
    assert small.depth == T.DEFAULT_DEPTH == 7
    terms = " + ".join(f"1/(1 + {k + 2}*((x - {k / 40:.3f})^2 + y^2 + z^2))" for k in range(20))
    big = lgshape.Surface(f"0.5 - ({terms})", ((-1,) * 3, (1,) * 3), tables=False)
    assert big.expr.size() > T.DEEP_MAX_NODES and big.depth == 6
    assert lgshape.Surface(LIBRARY["torus"](), depth=5).depth == 5


def test09_flat_boxes_get_cubic_cells(rng):
    """A plain expression's grid box: the box itself where it is near
    cubic, else the cube about it (same centre), so the cells are cubes;
    the search still keeps to the box. Oracle: float64 polynomial roots of
    a torus in its flat box (3.08 x 3.08 x 0.96) and in a box cut flat
    through its tube (z in [0, 0.2]: the cells outside the box hold surface
    that no ray may report), 4000 rays from outside aimed into the box."""
    import lgshape
    from lgshape.reference import clip_to_box, polynomial_roots
    from lgshape.trace import _grid_box
    lo, hi = np.array([-1.0, -1.5, 0.0]), np.array([1.0, 1.5, 1.5])
    assert [v.tolist() for v in _grid_box(lo, hi)] == [lo.tolist(), hi.tolist()]
    glo, ghi = _grid_box(np.array([-1.5, -1.5, -0.2]), np.array([1.5, 1.5, 0.4]))
    assert np.allclose(glo, [-1.5, -1.5, -1.4]) and np.allclose(ghi, [1.5, 1.5, 1.6])

    def F(X, Y, Z):
        return (X**2 + Y**2 + Z**2 + 1 - 0.16)**2 - 4 * (X**2 + Y**2)
    spec = LIBRARY["torus"]()
    for box in (spec.bbox, ((-1.5, -1.5, 0.0), (1.5, 1.5, 0.2))):
        surf = lgshape.Surface(spec.expr, box)
        lo, hi = (np.asarray(v, float) for v in box)
        assert np.allclose(np.ptp(surf.grid.hi - surf.grid.lo), 0)        # a cube
        assert np.all(surf.grid.lo <= lo) and np.all(surf.grid.hi >= hi)
        c = 0.5 * (lo + hi)
        o = c + 3.0 * rng.normal(size=(4000, 3))
        d = lo + (hi - lo) * rng.uniform(0, 1, (4000, 3)) - o
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        o, d = o.astype(np.float32), d.astype(np.float32)
        res = surf.trace(o, d)
        t0, t1 = clip_to_box(o.astype(float), d.astype(float), lo, hi)
        roots = polynomial_roots(F, 4, o.astype(float), d.astype(float), t0, t1)
        real = np.where((np.abs(roots.imag) < 1e-9) & (roots.real >= t0[:, None])
                        & (roots.real <= t1[:, None]), roots.real, np.inf).min(1)
        hit, t = np.asarray(res.hit), np.asarray(res.t64)
        tol = 1e-5 * surf.diagonal
        clear = np.isfinite(real) | (t1 < t0)                 # a root, or no box
        assert np.all(hit[np.isfinite(real)]), "a root in the box was missed"
        root = np.isfinite(real)
        assert np.all(np.abs(t[root] - real[root]) < tol)
        assert not hit[~np.isfinite(real) & clear].any()
        assert np.isfinite(real).sum() > 500
