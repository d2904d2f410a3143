"""The benchmark's gradients section (lgshape.bench.projective): lg_prb on an
implicit surface against Mitsuba's prb_projective on its marching-cubes
mesh, at a tiny size (the figures themselves are in docs/BENCHMARKS.md).

Oracles: the mesh's vertices (scikit-image's marching cubes) lie on the
surface they sample, to the grid's resolution (the torus's own f); the
vertices' motion dv/dR is the torus's (unit, radial in its plane); the
section's targets follow their definitions from the records; the report
has one row per record.
"""
from __future__ import annotations

import math

import numpy as np

from lgshape.bench import projective as P


def test01_mesh_and_its_motion():
    grid = 40
    v, faces, dv = P._torus_mesh(0.75, grid)
    M = P._rot_x(P.TORUS_TILT)
    q = v @ M                                    # back to the torus's frame
    f = np.sqrt((np.hypot(q[:, 0], q[:, 1]) - 0.75) ** 2 + q[:, 2] ** 2) - 0.28
    cell = 2.8 / (grid - 1)
    assert np.abs(f).max() <= cell                # linear interpolation within a cell
    assert np.allclose(np.linalg.norm(dv, axis=1), 1.0, atol=1e-6)
    assert np.abs((dv @ M)[:, 2]).max() < 1e-6    # radial, in the torus's plane
    assert faces.min() >= 0 and faces.max() < len(v)


def test02_section_runs_and_reports():
    cfg = P.ProjectiveConfig(res=8, spp=4, seeds=2, fd_spp=16, fd_seeds=2, grid=24,
                             scenes=("torus",), time_res=12, time_reps=1)
    res = P.run(cfg=cfg)
    recs = res["records"]
    assert [r["integrator"] for r in recs] == ["lg_prb", "prb_projective"]
    for r in recs:
        assert r["finite"] and all(math.isfinite(r[k]) for k in ("ad", "fd", "t_grad"))
        assert r["ratio"] == r["t_grad"] / r["t_primal"]
    lg, pj = recs
    assert res["targets"]["torus"] == P.targets(lg, pj)
    assert res["targets"]["torus"]["time"] == (lg["ratio_big"] <= 3)
    assert lg["ratio_big"] == lg["t_grad_big"] / lg["t_primal_big"]
    lines = P.report(res)
    assert sum(1 for line in lines if line.startswith("| torus |")) == 2
