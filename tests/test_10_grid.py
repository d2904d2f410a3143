"""The pruning grid: conservative, sparse, bounded.

Oracle: brute-force sampling in float64. Surface points are found as sign
changes of f along many random segments (bisected to 1e-12); every such point
must lie in an occupied cell (or within the cell inflation of one). Memory is
checked against the dense alternative."""
import numpy as np
import pytest
from conftest import SURFACE_NAMES

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
