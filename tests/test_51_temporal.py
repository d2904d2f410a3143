"""Temporal stability (:mod:`lgshape.bench.temporal`) and the animation scenes.

Oracles: the float64 reference of the temporal benchmark,
:func:`lgshape.bench.temporal.spikes_reference` (a windowed float64 scan of
the spikes' f with bisection), checked here against the plain dense float64
scan :func:`lgshape.bench.stability.nearest_root` (40000 steps along the whole ray
in the box), and used as the oracle of the quick run: lgshape has no wrong
thin-feature pixel (a pixel whose float64 hit point is on a spike) in any
frame. The flicker measure on hand-worked frames (a pixel that a method
catches, loses and catches again while the truth does not change flickers
twice; a spike missed in every frame does not flicker); on the quick run it
is 0 for the oracle itself and positive for a coarse march (steps of
diag/64, several times a spike's width, catch the spikes in some frames
only). The animation scenes render two frames through
``lgshape render --frames 2 -D time=0:1`` at 16x12, 1 spp, and ``$time``
reaches the expression (the two blobs frames differ).
"""
import pathlib

import lgshape  # noqa: F401  (before mitsuba: sets up libLLVM)
import numpy as np
import OpenEXR
import pytest

from lgshape.bench import temporal as bt
from lgshape import cli
from lgshape.bench import stability

FIELDS = ("method", "setting", "mrays_per_s", "wrong_feature_per_frame",
          "wrong_feature_pixels_per_frame", "wrong_pixels_per_frame", "frames_with_wrong_feature",
          "wrong_feature_mean", "wrong_feature_max", "wrong_pixel_mean", "flicker",
          "flicker_per_pair", "missed_toggles", "excess_toggles")


@pytest.fixture(scope="module")
def quick():
    return bt.run(quick=True)


def records(results, method):
    return [r for r in results["records"] if r["method"] == method]


def test01_quick_run_records(quick, tmp_path):
    frames = bt.QUICK.frames
    methods = {r["method"] for r in quick["records"]}
    assert {"oracle", "lgshape", "sphere_trace", "march", "sdfgrid", "mesh"} <= methods
    for r in quick["records"]:
        for f in FIELDS:
            assert f in r, (r["method"], f)
        assert len(r["wrong_feature_per_frame"]) == frames
        assert len(r["wrong_pixels_per_frame"]) == frames
        assert len(r["flicker_per_pair"]) == frames - 1
        assert all(0 <= v <= 1 for v in r["wrong_feature_per_frame"])
    meta = quick["meta"]
    assert len(meta["feature_pixels_per_frame"]) == frames
    assert min(meta["feature_pixels_per_frame"]) > 10      # the spikes are seen in every frame
    # chart and report from the same dict
    path = bt.chart(quick, str(tmp_path / "t.png"))
    with open(path, "rb") as fh:
        assert fh.read(8) == b"\x89PNG\r\n\x1a\n"
    lines = bt.report(quick)
    assert lines[0].startswith("## Temporal stability")
    # the table: a header and a row per method and setting (the oracle has none)
    assert sum(ln.startswith("| ") for ln in lines) == len(quick["records"])


def test02_reference_matches_dense_scan():
    """spikes_reference against nearest_root's dense scan (40000 steps):
    the same hits and misses, roots within 1e-9, on rays over thin-feature
    pixels and random pixels of one frame."""
    spec = bt.animation_spec()
    o, d = bt.orbit_rays(48, 25.0, bt.QUICK)
    t = bt.spikes_reference(spec, o, d)
    p = o + np.where(np.isfinite(t), t, 0)[:, None] * d
    on_spike = np.linalg.norm(p, axis=1) > bt.FEATURE_RADIUS * bt.CORE
    feat = np.flatnonzero(np.isfinite(t) & on_spike)
    rng = np.random.default_rng(3)
    sel = np.concatenate([rng.choice(feat, min(40, len(feat)), replace=False),
                          rng.choice(len(o), 40, replace=False)])
    ref = stability.nearest_root(spec, o[sel], d[sel], steps=40000)
    assert np.array_equal(np.isfinite(ref), np.isfinite(t[sel]))
    both = np.isfinite(ref)
    assert both.sum() > 40
    assert np.max(np.abs(ref[both] - t[sel][both])) < 1e-9


def test03_lgshape_exact_every_frame(quick):
    """Oracle: spikes_reference (float64). lgshape has no wrong thin-feature
    pixel, and no wrong pixel at all, in any frame."""
    (lg,) = records(quick, "lgshape")
    assert lg["wrong_feature_pixels_per_frame"] == [0] * bt.QUICK.frames
    assert lg["frames_with_wrong_feature"] == 0
    assert lg["wrong_pixel_mean"] == 0
    assert lg["flicker"] == 0


def test04_flicker_oracle_and_march(quick):
    (oracle,) = records(quick, "oracle")
    assert oracle["flicker"] == 0 and oracle["wrong_pixel_mean"] == 0
    assert oracle["missed_toggles"] == 0 and oracle["excess_toggles"] == 0
    assert sum(quick["meta"]["oracle_toggles_per_pair"]) > 0   # the motion is seen
    coarse = next(r for r in records(quick, "march") if r["setting"] == "step diag/64")
    assert coarse["flicker"] > 0
    assert coarse["frames_with_wrong_feature"] > 0


def test05_flicker_hand_worked():
    """Two pixels, three frames, rays along +z from z = -5: the truth hits a
    spike on pixel 0 (t = 4, |p| = 1 > 1.1 core) in every frame and nothing
    on pixel 1. A method that catches pixel 0 in frames 0 and 2 only flickers
    once per pair; one that never catches it does not flicker but is wrong in
    every frame; the truth against itself: 0."""
    frames = 3
    o = np.tile([[0.0, 0.0, -5.0]], (2 * frames, 1)).astype(np.float32)
    d = np.tile([[0.0, 0.0, 1.0]], (2 * frames, 1)).astype(np.float32)
    ref = np.tile([4.0, np.inf], frames)
    diag = 1.0

    def judge(t):
        return bt.judge_frames(t, np.isfinite(t), ref, o, d, diag, frames)[0]
    m = judge(np.array([4.0, np.inf, np.inf, np.inf, 4.0, np.inf]))
    assert m["flicker_per_pair"] == [1, 1] and m["flicker"] == 1.0
    assert m["wrong_feature_pixels_per_frame"] == [0, 1, 0]
    assert m["frames_with_wrong_feature"] == pytest.approx(1 / 3)
    assert m["excess_toggles"] == 1.0 and m["missed_toggles"] == 0
    m = judge(np.full(2 * frames, np.inf))
    assert m["flicker"] == 0 and m["wrong_feature_per_frame"] == [1.0, 1.0, 1.0]
    m = judge(ref.copy())
    assert m["flicker"] == 0 and m["wrong_pixel_mean"] == 0
    # A hit far behind the spike (the core seen through a missed spike) is wrong.
    m = judge(np.array([4.0, np.inf, 4.5, np.inf, 4.0, np.inf]))
    assert m["wrong_feature_pixels_per_frame"] == [0, 1, 0]
    assert m["flicker"] == 1.0         # spike -> core -> spike while the truth stays a spike


def read_rgb(path):
    with OpenEXR.File(str(path)) as f:
        return np.asarray(f.channels()["RGB"].pixels)


@pytest.mark.parametrize("name", ["anim_spikes", "anim_blobs"])
def test06_anim_scenes_render_two_frames(name, tmp_path):
    scene = str(pathlib.Path(__file__).parent.parent / "scenes" / f"{name}.xml")
    out = tmp_path / "f.exr"
    assert cli.main(["render", scene, "-o", str(out), "--frames", "2", "-D", "time=0:1",
                     "-D", "resx=16", "-D", "resy=12", "-D", "spp=1"]) == 0
    imgs = [read_rgb(tmp_path / f"f_{k:04d}.exr") for k in range(2)]
    for k, img in enumerate(imgs):
        assert img.shape == (12, 16, 3) and np.all(np.isfinite(img)) and img.mean() > 0.01
        assert (tmp_path / f"f_{k:04d}.png").stat().st_size > 0
    # the surface moves: the time reached the expression (or the transform)
    assert np.abs(imgs[0] - imgs[1]).max() > 0.05
