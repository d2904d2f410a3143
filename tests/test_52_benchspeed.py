"""The speed section of the benchmark (lgshape.bench.speed).

Oracles: analytic ray-sphere intersection (the nearest entry t = -b -
sqrt(b^2 - c) of a unit-direction ray into the unit sphere) for lgshape's
shadow-ray answers, and lgshape's own camera trace (a shadow ray along a
camera ray is occluded iff its t_max reaches past the traced hit). The quick
run is checked for its records' fields and for positive finite ratios, not
for speed.
"""
import math
import os

import numpy as np
import pytest

import lgshape
from conftest import JIT
from lgshape.bench import speed as S
from lgshape.surfaces import sphere


@pytest.fixture(scope="module")
def quick():
    import mitsuba as mi
    mi.set_variant(S.VARIANT)
    lines = []
    return S.run(lines.append, quick=True), lines


def analytic_entry(o, d):
    """Nearest t >= 0 where o + t d (|d| = 1) enters the unit sphere (float64,
    inf where it misses), and the discriminant."""
    o, d = o.astype(np.float64), d.astype(np.float64)
    a = np.sum(d * d, 1)
    b = np.sum(o * d, 1) / a
    c = (np.sum(o * o, 1) - 1.0) / a
    disc = b * b - c
    with np.errstate(invalid="ignore"):
        t = -b - np.sqrt(disc)
    return np.where((disc >= 0) & (t >= 0), t, np.inf), disc


def test01_quick_run_records(quick):
    res, lines = quick
    rows = res["rows"]
    surfaces = S.QUICK.surfaces
    assert {(r["surface"], r["kind"]) for r in rows} == {(s, k) for s in surfaces
                                                         for k in S.KINDS}
    for r in rows:
        assert r["rays"] > 0
        for m in S.METHODS:
            rec = r[m]
            for key in ("setting", "seconds", "mrays_per_s", "hit_fraction", "evals_per_ray",
                        "iterations_per_ray", "capped"):
                assert key in rec, (r["surface"], r["kind"], m, key)
            assert rec["seconds"] > 0 and math.isfinite(rec["mrays_per_s"])
            assert len(rec["samples"]) == S.QUICK.repeats
            assert rec["seconds"] == pytest.approx(float(np.median(rec["samples"])))
            if m != "lgshape":
                assert 0.0 <= rec["agree"] <= 1.0
        lg = r["lgshape"]
        assert lg["evals_per_ray"] > 0
        # a quadric's rays may be answered from the whole ray's quadratic
        # form before any search iteration (the sphere's shadow rays)
        quadric = lgshape.Surface(lgshape.surfaces.LIBRARY[r["surface"]]()).quadric
        assert lg["iterations_per_ray"] > 0 or (quadric and lg["iterations_per_ray"] == 0), r
        assert lg["capped"] == 0, r                    # no library ray reaches the cap
        assert r["sphere_trace"]["evals_per_ray"] > 0
        assert r["mesh"]["evals_per_ray"] is None and r["mesh"]["triangles"] > 0
        for key in ("ratio_sphere", "ratio_mesh"):
            assert r[key] is not None and 0 < r[key] < math.inf
        assert r["target_sphere"] == (1.0 if r["surface"] == "sphere" else 2.0)
        assert r["target_mesh"] == 1.0
        # a ratio: the median of the rounds' paired ratios
        assert r["ratio_mesh"] == pytest.approx(float(np.median(
            np.divide(r["mesh"]["samples"], lg["samples"]))))
        assert r["met_sphere"] == (r["ratio_sphere"] >= r["target_sphere"])
        assert r["met_mesh"] == (r["ratio_mesh"] >= r["target_mesh"])
    # the camera rays are res^2; shadow rays start where the camera rays hit
    for s in surfaces:
        by = {r["kind"]: r for r in rows if r["surface"] == s}
        assert by["camera"]["rays"] == S.QUICK.res ** 2
        assert by["incoherent"]["rays"] == S.QUICK.incoherent
        assert by["shadow"]["rays"] == round(by["camera"]["lgshape"]["hit_fraction"]
                                             * S.QUICK.res ** 2)
        # the guaranteed tracer and the mesh see the same picture, up to the
        # mesh's approximation at the silhouettes
        assert by["camera"]["mesh"]["agree"] > 0.97


def test07_timed_together_interleaves_rounds():
    """Oracle: the order of the runners' calls, recorded by the runners; the
    paired ratio by hand (median of per-round quotients)."""
    from lgshape.bench import common
    calls = []

    def runner(key):
        def run():
            calls.append(key)
            return (JIT.Float([1.0]),)
        return common.Runner(key, "", run, lambda out: key, lambda t: None, 0, 0.0)
    res = common.timed_together({k: runner(k) for k in "abc"}, repeats=4)
    # warm-up and calibration of each, then rounds in rotated order
    assert calls == list("aabbcc") + list("abc") + list("bca") + list("cab") + list("abc")
    for k in "abc":
        out, med, samples = res[k]
        assert out == k and len(samples) == 4 and med == float(np.median(samples))
    assert common.paired_ratio([2.0, 9.0, 3.0], [1.0, 3.0, 3.0]) == 2.0


def test02_quick_run_render_and_latency(quick):
    res, _ = quick
    c = res["cornell"]
    assert c["meshed"] == ["tangle"] and c["triangles"]["tangle"] > 0
    for key in ("lg_path", "path"):
        assert c[key]["seconds"] > 0 and c[key]["first_s"] > 0
    assert 0 < c["ratio"] < math.inf and c["met"] == (c["ratio"] <= S.TARGET_CORNELL)
    # the same picture: the mesh wound as lgsurface's normals (a one-sided
    # conductor seen from behind would be black)
    assert c["path"]["image_mean"] == pytest.approx(c["lg_path"]["image_mean"], rel=0.1)
    # the gradient pass (lg_prb, prb on the mesh) and the emitters' noise:
    # records of each case, the ratios from their own timings
    g = res["gradients"]
    for key in ("lg_prb", "prb", "lg_prb_shape"):
        assert g[key]["primal_s"] > 0 and g[key]["gradient_s"] > 0 and g[key]["grad_norm"] > 0
    e = res["emitters"]["methods"]
    assert set(e) == {"lg_path, lgsurface", "path, native sphere", "path, mesh"}
    assert all(m["mse"] > 0 and m["seconds"] > 0 for m in e.values())
    md = res["media"]["methods"]
    assert all(m["seconds"] > 0 and m["image_mean"] > 0 for m in md.values())
    # host time: the records, no kernel compiled once warm (kernel history),
    # and frozen, traced and native renders of one scene agree in the mean
    ho = res["host"]["methods"]
    assert set(ho) == {"lg_path", "lg_path, traced", "path, native sphere"}
    for m in ho.values():
        assert m["seconds"] > 0 and m["kernel_s"] >= 0 and m["compiled_after_warmup"] == 0
        assert m["ratio"] > 0
    assert ho["lg_path"]["image_mean"] == pytest.approx(ho["path, native sphere"]["image_mean"],
                                                        rel=0.05)
    k = res["compile"]
    for key in S.PROBES:
        assert "error" not in k[key], k[key]
        assert k[key]["first_s"] > 0 and k[key]["second_s"] > 0
    assert k["cold"]["kernels_compiled"] > 0            # an empty cache compiles
    assert k["cold"]["cache_files"] > 0                 # ... and fills $HOME/.drjit
    assert k["warm_again"]["cache_files"] >= k["cold"]["cache_files"]
    # the oracle of kernel reuse: Dr.Jit's kernel history of the warm runs
    assert k["warm"]["kernels_compiled"] == 0 and k["warm_again"]["kernels_compiled"] == 0


def test03_shadow_rays_analytic_sphere(rng):
    """Oracle: analytic. Shadow rays from points outside the unit sphere
    towards points near its centre, with t_max anywhere from 0 to past the
    far side: occluded iff the ray enters the sphere before t_max. Rays within
    1e-4 of tangency or with the entry within 1e-4 of t_max are left out."""
    surf = lgshape.Surface(sphere())
    n = 4000
    o = rng.normal(size=(n, 3))
    o = o / np.linalg.norm(o, axis=1, keepdims=True) * rng.uniform(1.02, 1.1, (n, 1))
    target = rng.uniform(-1.6, 1.6, (n, 3))
    d = target - o
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    o = o.astype(np.float32)
    t_max = rng.uniform(0.0, 2.5, n).astype(np.float32)
    t_in, disc = analytic_entry(o, d)
    want = t_in <= t_max
    clear = (np.abs(disc) > 1e-4) & ~(np.abs(t_in - t_max) < 1e-4)
    assert want[clear].mean() > 0.1 and (~want[clear]).mean() > 0.1    # both answers occur
    got = np.asarray(surf.occluded(o, d, t_max)).astype(bool)
    bad = np.flatnonzero(clear & (got != want))
    assert len(bad) == 0, [(o[i], d[i], t_max[i], t_in[i]) for i in bad[:5]]


def test04_shadow_rays_from_camera_hits(rng):
    """The section's shadow rays on the sphere: from lgshape's camera hits,
    offset along the normal towards the camera, to the light. Oracle:
    analytic (the segment to the light enters the unit sphere); and lgshape's
    own camera trace: a shadow ray along each camera ray is occluded iff its
    t_max reaches past the traced hit."""
    from lgshape.camera import primary_rays
    spec = sphere()
    surf = lgshape.Surface(spec)
    o, d = primary_rays(spec.bbox, 48)
    r = surf.trace(o, d)
    hit, t64 = np.asarray(r.hit).astype(bool), np.asarray(r.t64, np.float64)
    assert 0.2 < hit.mean() < 0.9

    # along the camera rays: occluded iff t_max is past the hit
    k = np.flatnonzero(hit)
    beyond = np.asarray(surf.occluded(o[k], d[k], (t64[k] * 1.001).astype(np.float32)))
    short = np.asarray(surf.occluded(o[k], d[k], (t64[k] * 0.999).astype(np.float32)))
    assert beyond.all() and not short.any()
    miss = np.flatnonzero(~hit)
    assert not np.asarray(surf.occluded(o[miss], d[miss], np.float32(100.0))).any()

    # the section's shadow rays, against the analytic segment test
    so, sd, st, idx = S.shadow_rays(spec, surf, o, d, t64, hit)
    assert np.array_equal(idx, k)
    diag = float(np.linalg.norm(np.subtract(spec.bbox[1], spec.bbox[0])))
    assert np.allclose(np.linalg.norm(so, axis=1), 1.0 + S.SHADOW_OFFSET * diag, atol=1e-5)
    light = S.light_position(spec)
    assert np.allclose(so.astype(np.float64) + st[:, None].astype(np.float64) * sd, light,
                       atol=1e-4)
    t_in, disc = analytic_entry(so, sd)
    want = t_in <= st
    clear = np.abs(disc) > 1e-4
    got = np.asarray(surf.occluded(so, sd, st)).astype(bool)
    assert want[clear].any() and (~want[clear]).any()
    assert np.array_equal(got[clear], want[clear])


def test05_mesh_and_scene_rewrite(tmp_path):
    """The marching-cubes mesh's faces point towards f > 0 (outwards on the
    sphere); the cornell scene's lgsurface becomes a ply shape with the same
    transform and BSDF, and lg_path becomes path."""
    from lgshape.bench.baselines import sample_grid
    spec = sphere()
    v, faces = S.marching_mesh(spec, sample_grid(spec, 24))
    tri = v[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert np.all(np.sum(fn * tri.mean(1), axis=1) > 0)
    text, names = S.mesh_scene_xml(S.CORNELL, lambda name: str(tmp_path / f"{name}.ply"))
    assert names == ["tangle"]
    assert 'type="lgsurface"' not in text and 'type="lg_path"' not in text
    assert '<integrator type="path">' in text and 'type="ply"' in text
    assert f'value="{tmp_path / "tangle.ply"}"' in text
    assert 'name="Au"' not in text and 'value="Au"' in text       # the BSDF kept
    assert 'angle="35"' in text                                   # the transform kept


def test06_report_and_chart(quick, tmp_path):
    res, _ = quick
    lines = S.report(res)
    assert lines[0].startswith("## Speed against the alternatives")
    header = next(i for i, ln in enumerate(lines) if ln.startswith("| surface | ray kind | rays |"))
    assert lines[header + 1].startswith("|---")
    table = [ln for ln in lines[header + 2:] if ln.startswith("| ")]
    assert len(table) >= len(res["rows"])
    assert any("met" in ln for ln in lines[header:header + 1])
    assert any(ln.startswith("### Render: cornell.xml") for ln in lines)
    assert any(ln.startswith("### First-image latency") for ln in lines)
    assert any("Ratio lg_path / path" in ln for ln in lines)
    path = S.chart(res, str(tmp_path / "speed.png"))
    assert os.path.getsize(path) > 1000
    import json
    json.dumps(res, allow_nan=False)                  # JSON-serialisable as it is


def test08_command_line_ray_counts(tmp_path, capsys):
    """--res and --incoherent set the ray counts (for a GPU, whose launch
    costs need more rays than the CPU's defaults): oracle, the records'
    ray counts (res^2 camera rays, the incoherent count) and the config;
    a count below 1 is refused, naming the option."""
    import json
    out = tmp_path / "bs"
    assert S.main(["--out", str(out), "--quick", "--surfaces", "sphere", "--no-cornell",
                   "--no-compile", "--res", "12", "--incoherent", "333"]) == 0
    res = json.loads((out / "speed.json").read_text())
    rays = {r["kind"]: r["rays"] for r in res["rows"]}
    assert rays["camera"] == 144 and rays["incoherent"] == 333
    assert 0 < rays["shadow"] <= 144
    assert res["meta"]["config"]["res"] == 12 and res["meta"]["config"]["incoherent"] == 333
    with pytest.raises(SystemExit) as err:
        S.main(["--out", str(out), "--incoherent", "0"])
    assert err.value.code == 2 and "--incoherent must be a positive integer" in capsys.readouterr().err
