"""Templates and tables (many primitives): per-cell rows and the search over them.

Oracles: analytic ray-sphere and ray-box roots (unions, CSG), float64
polynomial roots piecewise between the kernels' support boundaries (blends),
brute-force float64 scans (smooth unions), and the whole expression
evaluated over every row in float64 (per-cell rows).
"""
from __future__ import annotations

import numpy as np
import pytest

import lgshape
import lgshape.primitives as P
from lgshape import tables
from lgshape.arraymath import NUMPY
from lgshape.expr import evaluate
from lgshape.reference import along, clip_to_box, first_sign_change, polynomial_roots

from oracles import check_first_roots, sphere_roots


def numpy_F(tf):
    """F(x, y, z) over every row, float64 (any array shapes)."""
    def F(x, y, z):
        shape = np.broadcast(x, y, z).shape
        p = np.stack([np.broadcast_to(v, shape).reshape(-1) for v in (x, y, z)], 1)
        return tables.evaluate_points(tf, p).reshape(shape)
    return F


def random_spheres(rng, n, scale=0.6):
    c = rng.uniform(-1, 1, (n, 3))
    r = scale * n ** (-1 / 3) * rng.uniform(0.5, 1.0, n)
    return c, r


def rays_at(rng, surf, n, incoherent=False):
    lo, hi = surf.lo, surf.hi
    if incoherent:      # random origins in the box, random directions
        o = lo + (hi - lo) * rng.uniform(0, 1, (n, 3))
    else:               # from outside, aimed at random points of the box
        o = rng.normal(size=(n, 3))
        o = 0.5 * (lo + hi) + 2.5 * np.linalg.norm(hi - lo) * o / np.linalg.norm(o, axis=1)[:, None]
    target = lo + (hi - lo) * rng.uniform(0, 1, (n, 3))
    d = target - o if not incoherent else rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    return o.astype(np.float32), d.astype(np.float32)


def union_roots(o, d, c, r):
    """Roots of min_i (|p - c_i| - r_i) along rays: each sphere's roots where
    the point is in no other sphere (n, 2N) complex, NaN elsewhere."""
    o, d = o.astype(np.float64), d.astype(np.float64)
    roots = np.concatenate([sphere_roots(o, d, c[i], r[i]) for i in range(len(c))], 1)
    own = np.repeat(np.arange(len(c)), 2)
    with np.errstate(invalid="ignore"):
        p = o[:, None, :] + roots.real[..., None] * d[:, None, :]           # (n, 2N, 3)
        dist = np.sqrt(((p[:, :, None, :] - c[None, None]) ** 2).sum(-1)) - r    # (n, 2N, N)
        dist[:, np.arange(len(own)), own] = np.inf
        inside_other = (dist < 0).any(-1)
    return np.where(inside_other, np.nan, roots)


# ---------------------------------------------------------------------------
# Per-cell rows: f over the kept rows equals f over every row
# ---------------------------------------------------------------------------

def models(rng):
    c, r = random_spheres(rng, 120)
    return {
        "union": P.union(P.spheres(c, r)),
        "smooth_union": P.smooth_union(P.spheres(c, r), P.boxes(c[:30] + 0.05, 0.05), k=0.06),
        "blend": P.blend(P.spheres(c, 2.2 * r), P.capsules(c[:20], c[20:40], 0.12),
                         P.tori(c[40:55], 0.12, 0.04), P.boxes(c[60:80], 0.06, 0.03),
                         threshold=0.3),
    }


@pytest.mark.parametrize("name", ["union", "smooth_union", "blend"])
def test_cell_rows_are_exact(name):
    """Oracle: f over every row (float64). At random points of the row cells
    (the cells whose rows a search segment uses, holding every occupied
    cell), the kept rows give exactly f; in the pruned cells f has one sign."""
    rng = np.random.default_rng(5)
    tf = models(rng)[name]
    lo, hi = (np.array(v) for v in tf.bbox)
    depth = 5
    cr = tables.build(tf, lo, hi, depth)
    size = (hi - lo) / 2 ** depth
    assert cr.up == tables.ROW_UP
    assert {tuple(c_) for c_ in cr.cells >> cr.up} == {tuple(c_) for c_ in cr.row_cells}
    k = rng.integers(0, len(cr.row_cells), 6000)
    # over the inflated row cell: the search evaluates its rows that far out
    infl = tables.ROW_INFLATE
    p = lo + (cr.row_cells[k] + rng.uniform(-infl, 1 + infl, (len(k), 3))) * size * 2 ** cr.up
    full = tables.evaluate_points(tf, p)
    # f over each point's cell rows only, folded in the kernel's order
    agg = tf.aggregates[0]
    acc = np.full(len(k), np.nan)
    for gi, (_, g) in enumerate(tf.groups):
        start = np.searchsorted(cr.pair_cell[gi], np.arange(len(cr.row_cells) + 1))
        for step in range(int(np.diff(start).max(initial=0))):
            idx = start[k] + step
            ok = idx < start[k + 1]
            rows = cr.pair_row[gi][np.minimum(idx, len(cr.pair_row[gi]) - 1)]
            env = {v: p[:, i] for i, v in enumerate("xyz")}
            env.update({f"p{q}": g.params[rows, q] for q in range(g.width)})
            v = np.broadcast_to(evaluate(g.template, env, NUMPY), len(k))
            comb = evaluate(agg.combine, {"a": acc, "b": v}, NUMPY)
            acc = np.where(ok, np.where(np.isnan(acc), v, comb), acc)
    if agg.op == "add":
        acc = np.where(np.isnan(acc), 0.0, acc)
    kept = np.broadcast_to(evaluate(tf.outer, {"A0": acc, "x": p[:, 0], "y": p[:, 1],
                                               "z": p[:, 2]}, NUMPY), len(k))
    assert np.array_equal(kept, full) or np.abs(kept - full).max() <= 1e-12 * (1 + np.abs(full).max())
    n_pairs = sum(len(r_) for r_ in cr.pair_row)
    assert n_pairs < 0.5 * len(cr.row_cells) * tf.rows, "the rows were not pruned per cell"
    # pruned cells: one sign at their corners and inner points
    cells = rng.integers(0, 2 ** depth, (3000, 3))
    occ = {tuple(c_) for c_ in cr.cells}
    empty = cells[[tuple(c_) not in occ for c_ in cells]]
    q = lo + (empty[:, None, :] + rng.uniform(0, 1, (len(empty), 16, 3))) * size
    fv = tables.evaluate_points(tf, q.reshape(-1, 3)).reshape(len(empty), 16)
    assert np.all((fv > 0).all(1) | (fv < 0).all(1))


# ---------------------------------------------------------------------------
# The search over tables against analytic roots
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("incoherent", [False, True])
def test_union_of_spheres_analytic(incoherent):
    """Oracle: the nearest ray-sphere root outside every other sphere
    (closed form): the first root of every ray, 0 wrong rays."""
    rng = np.random.default_rng(11)
    c, r = random_spheres(rng, 80)
    tf = P.union(P.spheres(c, r))
    surf = lgshape.Surface(tf, depth=6)
    o, d = rays_at(rng, surf, 2500, incoherent)
    counts = check_first_roots(surf, numpy_F(tf), o, d, union_roots(o, d, c, r))
    assert counts["none"] < counts["rays"] and counts["simple"] > 250


def test_written_union_becomes_a_table():
    """A union written out as text is found as a table (same rows), and
    traces to the same analytic roots."""
    rng = np.random.default_rng(3)
    c, r = random_spheres(rng, 40)
    text = "min(" + ", ".join(f"sqrt((x - {float(a)!r})^2 + (y - {float(b)!r})^2 + (z - {float(e)!r})^2) - {float(s)!r}"
                              for (a, b, e), s in zip(c, r)) + ")"
    f = lgshape.parse(text)
    tf = tables.find_tables(f)
    assert tf is not None and tf.aggregates[0].op == "min" and tf.rows == 40
    assert np.array_equal(np.sort(tf.aggregates[0].groups[0].params, 0),
                          np.sort(np.column_stack([c, r]), 0))
    surf = lgshape.Surface(f, bbox=P.union(P.spheres(c, r)).bbox)
    assert surf.tables is not None
    o, d = rays_at(rng, surf, 1500)
    check_first_roots(surf, numpy_F(tf), o, d, union_roots(o, d, c, r))


def box_events(o, d, lo, hi):
    """(t_enter, t_exit) of rays through axis-aligned boxes (n, B)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d[:, None, :]
        ta, tb = (lo[None] - o[:, None, :]) * inv, (hi[None] - o[:, None, :]) * inv
        t0 = np.nanmax(np.minimum(ta, tb), -1)
        t1 = np.nanmin(np.maximum(ta, tb), -1)
    return np.where(t0 <= t1, t0, np.nan), np.where(t0 <= t1, t1, np.nan)


def test_csg_of_boxes_analytic():
    """CSG written as text, two tables: max(union of 24 boxes, -union of 20
    spheres) (boxes with holes). Oracle: the analytic events (box slab entries
    and exits, sphere entries and exits); the first root is the first event
    after which the ray is inside the solid (classified at the midpoint of
    the next gap between events, float64)."""
    rng = np.random.default_rng(8)
    blo = rng.uniform(-1, 0.6, (24, 3))
    bhi = blo + rng.uniform(0.1, 0.4, (24, 3))
    c, r = rng.uniform(-1, 1, (20, 3)), rng.uniform(0.08, 0.2, 20)
    boxes = ", ".join(
        f"max(abs(x - {float(0.5 * (a[0] + b[0]))!r}) - {float(0.5 * (b[0] - a[0]))!r}, "
        f"abs(y - {float(0.5 * (a[1] + b[1]))!r}) - {float(0.5 * (b[1] - a[1]))!r}, "
        f"abs(z - {float(0.5 * (a[2] + b[2]))!r}) - {float(0.5 * (b[2] - a[2]))!r})" for a, b in zip(blo, bhi))
    holes = ", ".join(f"sqrt((x - {float(p[0])!r})^2 + (y - {float(p[1])!r})^2 + (z - {float(p[2])!r})^2) - {float(s)!r}"
                      for p, s in zip(c, r))
    f = lgshape.parse(f"max(min({boxes}), -min({holes}))")
    tf = tables.find_tables(f)
    assert tf is not None and len(tf.aggregates) == 2
    surf = lgshape.Surface(f, bbox=((-1.3,) * 3, (1.3,) * 3))
    o32, d32 = rays_at(rng, surf, 3000)
    o, d = o32.astype(np.float64), d32.astype(np.float64)
    e0, e1 = box_events(o, d, blo, bhi)
    s = np.concatenate([sphere_roots(o, d, c[i], r[i]) for i in range(len(c))], 1)
    s = np.where(np.abs(s.imag) > 0, np.nan, s.real)
    t0, t1 = clip_to_box(o, d, surf.lo, surf.hi)
    ev = np.sort(np.concatenate([e0, e1, s, t0[:, None]], 1), 1)     # NaN last
    ev = np.where((ev >= t0[:, None]) & (ev <= t1[:, None]), ev, np.nan)
    ev = np.sort(ev, 1)
    mid = 0.5 * (ev[:, :-1] + ev[:, 1:])
    F = numpy_F(tf)
    with np.errstate(invalid="ignore"):
        inside = along(F, o, d, np.where(np.isnan(mid), 0.0, mid)) < 0
        inside &= ~np.isnan(mid) & (ev[:, 1:] - ev[:, :-1] > 1e-9)
    first = np.where(inside.any(1), ev[np.arange(len(o)), np.argmax(inside, 1)], np.inf)
    res = surf.trace(o32, d32)
    t64, hit = np.asarray(res.t64), np.asarray(res.hit)
    assert not np.asarray(res.capped).any()
    tol = 1e-6 * surf.diagonal
    # rays starting inside the solid are not counted (their first root is an exit)
    start_in = along(F, o, d, np.where(t0 < t1, t0 + 1e-9, 0.0)) < 0
    check = ~start_in & (t0 < t1)
    wrong = check & ~((np.isinf(first) & ~hit) | (hit & (np.abs(t64 - first) <= tol)))
    assert check.sum() > 2000 and np.isfinite(first[check]).sum() > 500
    assert not wrong.any(), (f"{int(wrong.sum())} wrong rays, e.g. "
                             f"{[(first[i], t64[i]) for i in np.flatnonzero(wrong)[:3]]}")


def test_union_of_boxes_builder_analytic():
    """Builder boxes (rounding 0): the first root is the nearest box entry
    (slab method), for rays starting outside every box."""
    rng = np.random.default_rng(2)
    cen = rng.uniform(-1, 1, (200, 3))
    half = rng.uniform(0.02, 0.12, (200, 3))
    tf = P.union(P.boxes(cen, half))
    surf = lgshape.Surface(tf)
    o32, d32 = rays_at(rng, surf, 3000)
    o, d = o32.astype(np.float64), d32.astype(np.float64)
    e0, _ = box_events(o, d, cen - half, cen + half)
    first = np.nanmin(np.where(e0 >= 0, e0, np.nan), 1)
    first = np.where(np.isnan(first), np.inf, first)
    res = surf.trace(o32, d32)
    t64, hit = np.asarray(res.t64), np.asarray(res.hit)
    tol = 1e-6 * surf.diagonal
    ok = (np.isinf(first) & ~hit) | (hit & (np.abs(t64 - first) <= tol))
    assert np.isfinite(first).sum() > 500
    assert ok.all(), f"{int((~ok).sum())} wrong rays"


def blend_roots(o, d, c, R, threshold, t0, t1):
    """All roots of threshold - sum K_i along rays: F is a polynomial of
    degree 6 between the support boundaries, so its roots are float64
    polynomial roots piece by piece."""
    F = numpy_F(P.blend(P.spheres(c, R), threshold=threshold))
    b = np.concatenate([sphere_roots(o, d, c[i], R[i]) for i in range(len(c))], 1)
    b = np.where(np.abs(b.imag) > 0, np.nan, b.real)
    b = np.clip(b, t0[:, None], t1[:, None])
    b = np.sort(np.concatenate([t0[:, None], b, t1[:, None]], 1), 1)
    out = []
    for k in range(b.shape[1] - 1):
        a_, b_ = b[:, k], b[:, k + 1]
        a_ = np.where(np.isnan(a_), t1, a_)
        b_ = np.where(np.isnan(b_), t1, b_)
        rt = polynomial_roots(F, 6, o, d, a_, b_)
        keep = (rt.real >= a_[:, None] - 1e-12) & (rt.real <= b_[:, None] + 1e-12) & (b_ > a_)[:, None]
        out.append(np.where(keep, rt, np.nan))
    return np.concatenate(out, 1), F


def test_blend_polynomial_roots():
    """A blend of 24 soft blobs: every ray's first root against float64
    polynomial roots between the kernels' support boundaries."""
    rng = np.random.default_rng(4)
    c = rng.uniform(-0.8, 0.8, (24, 3))
    R = rng.uniform(0.3, 0.55, 24)
    tf = P.blend(P.spheres(c, R), threshold=0.3)
    surf = lgshape.Surface(tf)
    o32, d32 = rays_at(rng, surf, 1500)
    o, d = o32.astype(np.float64), d32.astype(np.float64)
    t0, t1 = clip_to_box(o, d, surf.lo, surf.hi)
    roots, F = blend_roots(o, d, c, R, 0.3, t0, np.maximum(t1, t0))
    counts = check_first_roots(surf, F, o32, d32, roots)
    assert counts["simple"] > 200


def test_smooth_union_scan():
    """A smooth union of 60 spheres and 10 capsules. Oracle: a 2048-step
    float64 scan and bisection: where the scan finds a first sign change the
    kernel hits there (or earlier, at a float64-verified sign change); where
    it finds none, any hit must be a verified sign change."""
    rng = np.random.default_rng(9)
    c, r = random_spheres(rng, 60, 0.5)
    tf = P.smooth_union(P.spheres(c, r), P.capsules(c[:10], c[10:20], 0.05), k=0.08)
    surf = lgshape.Surface(tf)
    o32, d32 = rays_at(rng, surf, 200)
    o, d = o32.astype(np.float64), d32.astype(np.float64)
    F = numpy_F(tf)
    t0, t1 = clip_to_box(o, d, surf.lo, surf.hi)
    scan = first_sign_change(F, o, d, t0, t1, steps=2048)
    res = surf.trace(o32, d32)
    t64, hit = np.asarray(res.t64), np.asarray(res.hit)
    tol = 1e-6 * surf.diagonal
    h = 4e-6 * surf.diagonal
    with np.errstate(invalid="ignore"):
        verified = hit & (np.sign(along(F, o, d, t64 - h)) * np.sign(along(F, o, d, t64 + h)) <= 0)
    at_scan = hit & (np.abs(t64 - scan) <= tol)
    earlier = verified & (t64 < scan)
    ok = np.where(np.isfinite(scan), at_scan | earlier, ~hit | verified)
    assert np.isfinite(scan).sum() > 40
    assert ok.all(), f"{int((~ok).sum())} rays disagree with the scan"


# ---------------------------------------------------------------------------
# Kernels independent of the rows; builders and files
# ---------------------------------------------------------------------------

def test_kernels_reused_across_row_counts():
    """Tables of the same templates with other row counts and values run the
    same compiled kernels (Dr.Jit's kernel hashes are equal)."""
    import drjit as dr
    hashes = []
    for n, seed in ((30, 1), (300, 2)):
        rng = np.random.default_rng(seed)
        c, r = random_spheres(rng, n)
        surf = lgshape.Surface(P.union(P.spheres(c, r)), depth=6)   # (a depth is structure)
        o, d = rays_at(rng, surf, 256)
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        dr.kernel_history()                       # clear
        res = surf.trace(o, d)
        dr.eval(res.t, res.t64, res.hit, res.evals, res.iterations, res.capped, res.unresolved)
        dr.eval(surf.gradient(o))                  # normals: the cell lookup, all rows
        hist = dr.kernel_history()
        dr.set_flag(dr.JitFlag.KernelHistory, False)
        hashes.append(sorted(k["hash"] for k in hist if k.get("type") == dr.KernelType.JIT))
    assert hashes[0] and hashes[0] == hashes[1]


def test_primitives_file(tmp_path):
    rng = np.random.default_rng(6)
    c, r = random_spheres(rng, 20)
    parts = [P.spheres(c, r), P.capsules(c[:3], c[3:6], 0.05), P.boxes(c[:4], 0.05, 0.01),
             P.tori(c[:2], 0.1, 0.02)]
    path = tmp_path / "m.prims"
    P.save(str(path), *parts)
    tf = P.load(str(path), "union")
    ref = P.union(*parts)
    pts = rng.uniform(-1, 1, (500, 3))
    assert np.array_equal(tables.evaluate_points(tf, pts), tables.evaluate_points(ref, pts))
    bad = tmp_path / "bad.prims"
    bad.write_text("sphere 0 0 0 1\ncone 0 0 0 1\n")
    with pytest.raises(ValueError, match=r"bad.prims:2: unknown primitive 'cone'"):
        P.load(str(bad))
    bad.write_text("# c\nsphere 0 0 0\n")
    with pytest.raises(ValueError, match=r"bad.prims:2: sphere takes 4 numbers"):
        P.load(str(bad))
    bad.write_text("sphere 0 0 0 -1\n")
    with pytest.raises(ValueError, match="sphere 0: r must be positive"):
        P.load(str(bad))
    with pytest.raises(ValueError, match="smooth_union: k must be positive"):
        P.smooth_union(P.spheres(c, r), k=0)
    with pytest.raises(ValueError, match="interval"):
        lgshape.Surface(ref, L=10.0)
    with pytest.raises(ValueError, match="boxes in a blend need rounding > 0"):
        P.blend(P.boxes(c[:2], 0.1))


def test_tables_found_only_where_they_apply():
    """A written-out union with a hand-given search mode keeps the fused
    form (as before tables existed) and traces the same analytic roots."""
    rng = np.random.default_rng(13)
    c, r = random_spheres(rng, 20)
    text = "min(" + ", ".join(f"sqrt((x - {float(a)!r})^2 + (y - {float(b)!r})^2 + "
                              f"(z - {float(e)!r})^2) - {float(s)!r}"
                              for (a, b, e), s in zip(c, r)) + ")"
    surf = lgshape.Surface(text, bbox=((-1.3,) * 3, (1.3,) * 3), search="taylor")
    assert surf.tables is None
    o, d = rays_at(rng, surf, 300)
    check_first_roots(surf, numpy_F(P.union(P.spheres(c, r))), o, d, union_roots(o, d, c, r))


def test_smooth_union_box_holds_the_surface():
    """The smooth union lies below the union (by up to min((n - 1) k / 4,
    k), tables.smin_below): its box is that much larger, so f > 0 on the box
    (oracle: f over every row, float64)."""
    tf = P.smooth_union(P.spheres([[0, 0, 0], [0.15, 0, 0]], 0.1), k=0.8)
    lo, hi = (np.array(v) for v in tf.bbox)
    g = np.linspace(0, 1, 9)
    faces = []
    for axis in range(3):
        for side in (lo, hi):
            u, v = np.meshgrid(g, g)
            pts = lo + (hi - lo) * np.stack([u.ravel(), v.ravel(), u.ravel()], 1)
            pts[:, axis] = side[axis]
            pts[:, (axis + 1) % 3] = lo[(axis + 1) % 3] + (hi - lo)[(axis + 1) % 3] * u.ravel()
            pts[:, (axis + 2) % 3] = lo[(axis + 2) % 3] + (hi - lo)[(axis + 2) % 3] * v.ravel()
            faces.append(pts)
    assert np.all(tables.evaluate_points(tf, np.concatenate(faces)) > 0)


def test_smooth_union_of_coincident_spheres():
    """16 spheres at one centre, k = 0.75 (dyadic: the kernel's rows and k
    are the oracle's exactly): every distance is |p - c| - r, so the folded
    smooth minimum is |p - c| - r - D_16 with D_1 = 0, D_(j+1) = D_j +
    (k - D_j)^2 / (4k), a sphere of radius r + D_16 = 0.68 (it lies 0.43,
    more than k / 4, beyond the parts). Oracle: the ray-sphere root in
    float64; every ray aimed at the centre hits (the box reaches that far)."""
    c, r, k, n = np.array([0.5, 0.25, 0.0]), 0.25, 0.75, 16
    D = 0.0
    for _ in range(n - 1):
        D += max(k - D, 0.0) ** 2 / (4 * k)
    assert D > k / 4
    tf = P.smooth_union(P.spheres(np.tile(c, (n, 1)), r), k=k)
    surf = lgshape.Surface(tf)
    rng = np.random.default_rng(5)
    u = rng.normal(size=(400, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    o = np.float32(c + 2.0 * u)
    d = np.float32(-u + rng.uniform(-0.1, 0.1, (400, 3)))
    counts = check_first_roots(surf, numpy_F(tf), o, d,
                               sphere_roots(o.astype(np.float64), d.astype(np.float64),
                                            c, r + D))
    assert counts["none"] == 0 and counts["simple"] > 300


def test_builder_distances_match_closed_forms():
    """Oracle: closed-form distances (sphere, capsule, box, torus) in numpy,
    with dyadic parameters (exact in the builders' float32 storage)."""
    rng = np.random.default_rng(12)
    p = rng.uniform(-1.5, 1.5, (2000, 3))
    a, b = np.array([[0.125, -0.25, 0.375]]), np.array([[0.625, 0.25, 0.375]])
    ba = b - a
    h = np.clip(((p - a) * ba).sum(1) / (ba * ba).sum(), 0, 1)
    half, rr = np.array([0.3125, 0.1875, 0.5]), 0.0625
    q = np.abs(p - a) - (half - rr)
    cases = {
        "sphere": (P.spheres(a, 0.375), np.linalg.norm(p - a, axis=1) - 0.375),
        "capsule": (P.capsules(a, b, 0.25), np.linalg.norm(p - a - h[:, None] * ba, axis=1) - 0.25),
        "box": (P.boxes(a, [half], rr), np.linalg.norm(np.maximum(q, 0), axis=1)
                + np.minimum(q.max(1), 0) - rr),
        "torus": (P.tori(a, 0.6875, 0.1875), np.sqrt((np.hypot(*(p - a)[:, :2].T) - 0.6875) ** 2
                                                    + (p - a)[:, 2] ** 2) - 0.1875),
    }
    for name, (part, ref) in cases.items():
        got = tables.evaluate_points(P.union(part, part), p)
        assert np.allclose(got, ref, rtol=0, atol=1e-12), name
