"""The benchmark (`lgshape bench`) and its stability suite.

Oracles: closed-form sphere intersections (the stability reference); a
hand-worked verdict table (the judge, tangent rays excluded); and for the
quick benchmark run, failures known before running it: a shell 1e-4 thick is
invisible to a march of step diag/256 and to 64^3 samples, a 1e-2 spike to
64^3 samples, and a wall whose Lipschitz constant is at least 1000 leaves a
sphere tracer steps of at most 1e-3 (more than its 1024 steps allow), so it
caps, stops short or misses. lgshape must be right on every non-tangent ray.

The domain-and-scale group: its closed-form oracles against a dense float64
scan of f itself (where the scan can see the roots), and, in the quick run,
failures known before running it: a sign change across the pole of 1/x - 2
is a surface to every method that looks for sign changes (march, the grid
samples); exp(50 x) and x^200 give a global Lipschitz bound of 1e20 or more,
so sphere tracing's distance bound |f| / L is below its eps at the box entry
(false hits); a sphere of radius 1e-3 at 1e4, where float32 positions are
1e-3 apart, is lost by the float32 grid transform (sdfgrid) and the float32
mesh vertices; the seed's global constants do not exist for f with a pole,
a domain edge or a kink (refused).
"""
import json
import math

import numpy as np
import pytest

import lgshape  # noqa: F401  (before mitsuba / drjit)
from lgshape.bench import stability
from lgshape.surfaces import LIBRARY, Implicit, sphere

RECORD_FIELDS = ("surface", "method", "setting", "mrays_per_s", "evals_per_ray", "memory_bytes",
                 "wrong_hit_fraction", "depth_error_mean", "depth_error_max", "normal_error_deg")
STABILITY_FIELDS = ("case", "group", "method", "missed", "false_hits", "capped", "nans")

FEATURE_CASES = {"thin_spikes", "grazing", "tangent", "singular_cone", "singular_kummer",
                 "steep_wall", "origin_on_surface", "thin_shell"}
DOMAIN_CASES = {*(f"scaled_{s}_{k:g}" for s in ("sphere", "torus") for k in stability.SCALES),
                "exp_wall", "pow200", "hemisphere", "inverse_pole", "log_edge", "undefined_gap",
                "sdf_box", "sdf_round_box", "sdf_capsule", "sdf_cylinder",
                "sdf_smooth_union_poly", "sdf_smooth_union_lse", "far_sphere",
                "far_small_sphere", "far_small_sphere_origin", "degenerate_rays",
                *(f"table_far_{off:g}" for off in stability.TABLE_OFFSETS), "table_grazing_mixed"}


def test01_nearest_root_matches_closed_form(rng):
    """The reference on a unit sphere: polynomial roots and the scan against
    t = -b - sqrt(b^2 - c), beyond t_min (the far root from inside)."""
    spec = sphere()
    o = (3.0 * rng.normal(size=(500, 3)) / math.sqrt(3)).astype(np.float32)
    o[:100] *= 0.1                                    # origins inside the ball
    d = rng.normal(size=(500, 3))
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    o64, d64 = o.astype(np.float64), d.astype(np.float64)
    b = np.sum(o64 * d64, 1) / np.sum(d64 * d64, 1)
    c = (np.sum(o64 * o64, 1) - 1.0) / np.sum(d64 * d64, 1)
    disc = b * b - c
    with np.errstate(invalid="ignore"):
        near, far = -b - np.sqrt(disc), -b + np.sqrt(disc)
    t_min = 0.05
    want = np.where(disc < 0, np.inf,
                    np.where(near >= t_min, near, np.where(far >= t_min, far, np.inf)))
    for kwargs, tol in (({"degree": 2}, 1e-9), ({"steps": 4096}, 1e-9)):
        got = stability.nearest_root(spec, o, d, t_min, **kwargs)
        assert np.array_equal(np.isfinite(got), np.isfinite(want)), kwargs
        fin = np.isfinite(want)
        assert np.max(np.abs(got[fin] - want[fin])) < tol, kwargs


def test02_judge_counts_and_excludes_tangent_rays():
    """A hand-worked table: tolerance 1e-2 diagonals (the box [-1, 1]^3,
    diagonal 2 sqrt 3, so 0.0346)."""
    spec = Implicit("plane", lgshape.parse("x"), ((-1.0,) * 3, (1.0,) * 3))
    n = 7
    case = stability.Case("hand", "", spec, np.zeros((n, 3), np.float32),
                          np.ones((n, 3), np.float32), 0.0,
                          t_ref=np.array([1.0, np.inf, 2.0, 3.0, 1.0, 1.0, 1.0]),
                          tangent=np.array([0, 0, 1, 0, 0, 0, 1], bool), oracle="by hand")
    t = np.array([1.01, 0.5, np.inf, 5.0, np.inf, 0.5, np.nan])
    hit = np.isfinite(t)
    v = stability.judge(case, t, hit)
    # ray 0 right (within 0.0346), 1 false (no root), 2 tangent (excluded),
    # 3 missed (hit beyond the root), 4 missed, 5 false (in front of the
    # root), 6 tangent but NaN (NaNs always count).
    assert v == {"missed": 2, "false_hits": 2, "nans": 1, "tangent": 2, "rays": n}


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    """One `lgshape bench --quick` run through the command line."""
    from lgshape.cli import main
    out = tmp_path_factory.mktemp("bench")
    # (the speed, scale, temporal and projective sections have their own tests)
    assert main(["bench", "--quick", "--no-speed", "--no-scale", "--no-temporal",
                 "--no-projective", "--out", str(out)]) == 0
    with open(out / "results.json") as fh:
        return out, json.load(fh)


def test03_records_have_the_fields(quick):
    _, res = quick
    assert res["records"] and res["stability"]
    for r in res["records"]:
        for k in RECORD_FIELDS:
            assert k in r, k
        assert r["surface"] in LIBRARY
        assert r["mrays_per_s"] > 0 and math.isfinite(r["mrays_per_s"])
        assert 0.0 <= r["wrong_hit_fraction"] <= 1.0
        assert r["memory_bytes"] >= 0
        # Evaluations of f exist exactly for the methods that evaluate f.
        assert (r["evals_per_ray"] is None) == (r["method"] in ("sdfgrid", "mesh"))
    for r in res["stability"]:
        for k in STABILITY_FIELDS:
            assert k in r, k
        assert (r["capped"] is None) == (r["method"] in ("sdfgrid", "mesh"))
    methods = {r["method"] for r in res["records"]}
    assert methods == {"lgshape", "lgshape_global", "sphere_trace", "sphere_trace_relaxed",
                       "march", "sdfgrid", "mesh"}


def test04_one_chart_per_surface_and_a_report(quick):
    out, res = quick
    for name in {r["surface"] for r in res["records"]}:
        with open(out / "charts" / f"{name}.png", "rb") as fh:
            assert fh.read(8) == b"\x89PNG\r\n\x1a\n", name
    text = (out / "BENCHMARKS.md").read_text()
    assert "lgshape bench --quick" in text and "| thin_spikes |" in text
    # The domain-and-scale group has its own heading and table, after the first.
    assert text.index("### " + stability.FEATURES) < text.index("### Domain and scale")
    tail = text[text.index("### Domain and scale"):]
    assert "| scaled_torus_1e+30 |" in tail and "| far_small_sphere_origin (t64) |" in tail


def _stab(res, case, method):
    rows = [r for r in res["stability"] if r["case"] == case and r["method"] == method]
    assert rows, (case, method)
    return rows


def test05_lgshape_is_right_on_the_stability_suite(quick):
    """Zero missed and zero false hits on every non-tangent ray, no ray at
    the iteration cap, no NaN, with local bounds (both search modes)."""
    _, res = quick
    cases = {c["case"] for c in res["cases"]}
    assert cases == FEATURE_CASES | DOMAIN_CASES
    for case in FEATURE_CASES:
        for r in _stab(res, case, "lgshape"):
            assert (r["missed"], r["false_hits"], r["capped"], r["nans"]) == (0, 0, 0, 0), r
    # Tangent rays are listed, not hidden: the tangent case has some.
    assert _stab(res, "tangent", "lgshape")[0]["tangent_excluded"] > 0


def test06_baseline_failures_show(quick):
    _, res = quick
    for method in ("march", "sdfgrid", "mesh"):
        (r,) = _stab(res, "thin_shell", method)
        assert r["missed"] > r["rays"] // 4, r
    for method in ("sdfgrid", "mesh"):
        (r,) = _stab(res, "thin_spikes", method)
        assert r["missed"] > 0, r
    (r,) = _stab(res, "steep_wall", "sphere_trace")
    assert r["lipschitz_L"] >= 1000
    assert r["missed"] + r["false_hits"] + r["capped"] > r["rays"] // 4, r
    # And in the primary-ray records: spikes thinner than diag/64.
    spikes = [r for r in res["records"] if r["surface"] == "spikes" and r["method"] == "march"
              and r["setting"] == "step diag/64"]
    assert spikes and spikes[0]["wrong_hit_fraction"] > 0


def test07_lgshape_primary_rays_match_the_reference(quick):
    """lgshape's records against the float64 reference: no pixel wrong,
    depths to 1e-5 of the diagonal."""
    _, res = quick
    for r in res["records"]:
        if r["method"] == "lgshape":
            assert r["wrong_hit_fraction"] == 0.0, r
            assert r["depth_error_max"] < 1e-5, r


def test08_domain_oracles_match_a_scan():
    """The closed-form oracles of the domain cases against a 20000-step
    float64 scan of f itself, on the cases where a sign-change scan is a
    valid reference (no pole, no undefined gap, no domain edge next to a
    root; the scaled cases use the unscaled f's polynomial roots)."""
    checked = {"exp_wall", "pow200", "log_edge", "sdf_box", "sdf_round_box", "sdf_capsule",
               "sdf_cylinder", "far_sphere", "far_small_sphere", "scaled_sphere_1e-30",
               "scaled_torus_1e+30"}
    for case in stability.cases(scale=0.25, groups=(stability.DOMAIN,)):
        if case.name not in checked:
            continue
        with np.errstate(all="ignore"):
            scan = stability.nearest_root(case.surface, case.o, case.d, case.t_min, steps=20000)
        ref = case.t_ref
        assert np.array_equal(np.isfinite(scan), np.isfinite(ref)), case.name
        fin = np.isfinite(ref)
        assert fin.sum() > len(ref) // 4, case.name
        assert np.max(np.abs(scan[fin] - ref[fin])) < 1e-6 * case.diagonal, case.name


def test09_degenerate_rays_are_misses():
    """Zero, infinite and NaN directions, NaN and infinite origins: misses,
    none capped (the contract of lgshape.trace)."""
    import lgshape as lg
    (case,) = [c for c in stability.cases(groups=(stability.DOMAIN,))
               if c.name == "degenerate_rays"]
    assert not np.isfinite(case.d).all(1).all() and (np.abs(case.d).sum(1) == 0).any()
    r = lg.Surface(case.surface).trace(case.o, case.d)
    assert not np.asarray(r.hit).any() and not np.asarray(r.capped).any()


def test10_lgshape_is_right_on_the_domain_cases(quick):
    """Zero missed / false / capped / NaN for lgshape (both search modes) on
    every domain-and-scale case (the undefined gap, x (x - 0.6) / sqrt(x^2 -
    0.04), once crawled to the cap: a division by an undefined sqrt was
    [0, 0] before intervals could be empty)."""
    _, res = quick
    notes = {c["case"]: c for c in res["cases"]}
    for case in DOMAIN_CASES:
        assert notes[case]["group"] == stability.DOMAIN
        rows = _stab(res, case, "lgshape")
        assert len(rows) == 2, rows
        for r in rows:
            assert (r["missed"], r["false_hits"], r["capped"], r["nans"]) == (0, 0, 0, 0), r
    # The far cases judge lgshape on its float64 t (the search) and say so.
    for case in ("far_sphere", "far_small_sphere", "far_small_sphere_origin"):
        assert notes[case]["judge_t64"] and "t64" in notes[case]["description"]
        assert all(r["judged_on"] == "t64" for r in _stab(res, case, "lgshape"))
    assert all(r["judged_on"] == "t" for r in _stab(res, "far_sphere", "mesh"))


def test12_domain_baseline_failures_show(quick):
    """Failures known before running (see the module text)."""
    _, res = quick
    for method in ("march", "sdfgrid", "mesh"):          # the pole as a surface
        (r,) = _stab(res, "inverse_pole", method)
        assert r["false_hits"] > r["rays"] // 5, r
    for case in ("exp_wall", "pow200"):                    # |f| / L below eps at once
        (r,) = _stab(res, case, "sphere_trace")
        assert r["lipschitz_L"] >= 1e20 and r["false_hits"] > r["rays"] // 2, r
    for method in ("sdfgrid", "mesh"):                     # float32 at 1e4: 1e-3 apart
        (r,) = _stab(res, "far_small_sphere", method)
        assert r["missed"] + r["false_hits"] > r["rays"] // 4, r
    for case in ("hemisphere", "inverse_pole", "log_edge", "undefined_gap", "sdf_box"):
        (r,) = _stab(res, case, "lgshape_global")
        assert r["note"].startswith("refused"), r
    (r,) = _stab(res, "far_small_sphere_origin", "march")    # step < ulp(t): stalls, capped
    assert r["capped"] > 0 and r["missed"] >= r["capped"], r


def test05_scale_worker_and_report():
    """The scale section's measurement on a small case: the union's oracle
    (analytic nearest ray-sphere entry) finds 0 wrong rays, the blend's
    (a sign change of the whole f at every hit) too; the report has its
    table and the targets."""
    from lgshape.bench import scale
    recs = [scale.worker(kind, 10, "tables", 48, 1) for kind in ("union", "blend")]
    for r in recs:
        assert r["wrong"] == 0 and r["capped"] == 0 and r["hits"] > 100, r
        assert r["rows_per_cell"] >= 1.0 and r["steady_s"] > 0
    recs.append(dict(recs[0], n=1000))      # the verdicts need an N = 1000 row
    text = "\n".join(scale.report(recs, 48))
    assert "## Scale" in text and "| union | 10 | tables |" in text
    assert "build at N=1000 (s)" in text


@pytest.mark.parametrize("variant, says", [("scalar_rgb", "scalar variant"),
                                           ("no_such_variant", "unknown variant")])
def test11_bench_refuses_a_variant_it_cannot_use(variant, says, tmp_path, capsys):
    """``lgshape bench --variant``: a variant lgshape cannot render with ends
    the run before any section, with exit status 2 and the reason."""
    from lgshape.cli import main
    assert main(["bench", "--quick", "--variant", variant, "--out", str(tmp_path)]) == 2
    assert says in capsys.readouterr().err
    assert not (tmp_path / "results.json").exists()
