"""Frame sequences (``lgshape render --frames``, :mod:`lgshape.frames`).

Oracles: frame k of a sequence is the image of a single ``lgshape
render`` with frame k's values (the single render is the oracle, its values
the issue's formula a + (b - a) k / (N - 1), written with repr); frames
rendered on Dask workers (a real LocalCluster of worker processes, also
with one of them killed by its pid while it renders) are the frames rendered
in this process. "The same image" (:func:`same_image`): the same files byte
for byte, or else the same pixels up to the order of the float32 additions
of each pixel's samples, which Dr.Jit's threads may change between any two
renders (see below); resume is seen in the files' mtimes and
in which frames are rendered; atomic writes are seen as no temporary file
left and no frame file under its name after a write that fails halfway; the
video is read back with imageio-ffmpeg (its frame count and size).

The scene is small (24x24, 3 spp) and uses a box filter, so each sample
goes to one pixel. A pixel's samples are added in one thread's order unless
Dr.Jit splits them between two threads' blocks of lanes, which more threads
(smaller blocks) make likely: with 2 threads the renders here are identical
byte for byte; with 16 (dr.set_thread_count(16), or a 16-core machine), 1 or
2 of the 1728 values of a frame came out an ulp apart between two renders
(see lgshape/frames.py). The bound of :func:`same_pixels` is that of the sum
of n = spp nonnegative float32 values in two orders, 2 (n - 1) u of the sum,
plus the film's division by the summed weight in each render (u each), so
2 n u <= (2 n + 1) u, u = 2^-24; every frame here is one pass of
render.PASS_SAMPLES (more passes would add a rounding each). A PNG (8-bit)
may then differ by one level.
"""
import os
import re
import signal
import threading
import time

import lgshape  # noqa: F401  (before mitsuba: sets up libLLVM)
import numpy as np
import OpenEXR
import pytest
from conftest import sensor_xml

from lgshape import cli, frames, render

SCENE = """<scene version="3.0.0">
    <default name="spp" value="2"/>
    <default name="res" value="24"/>
    <default name="angle" value="0"/>
    <default name="R" value="1"/>
    <integrator type="lg_path"><integer name="max_depth" value="3"/></integrator>
    """ + sensor_xml("0, -4, 2", up="0, 0, 1") + """
    <emitter type="constant"/>
    <shape type="lgsurface">
        <string name="surface" value="torus"/>
        <float name="R" value="$R"/>
        <float name="r" value="0.3"/>
        <transform name="to_world"><rotate x="1" angle="$angle"/></transform>
        <bsdf type="diffuse"><rgb name="reflectance" value="0.8, 0.5, 0.2"/></bsdf>
    </shape>
</scene>
"""
N = 4
SWEEP = ["-D", "angle=0:90", "-D", "R=0.8:1.2", "-D", "spp=3"]


def values(k, n=N):
    """Frame k's values by the issue's formula (the last frame: b), as a
    single render is given them."""
    def lerp(a, b):
        return repr(a + (b - a) * k / (n - 1) if k < n - 1 else b)
    return {"angle": lerp(0.0, 90.0), "R": lerp(0.8, 1.2)}


def read_exr(path):
    with OpenEXR.File(str(path)) as f:
        return {name: np.asarray(ch.pixels) for name, ch in f.channels().items()}


def temporaries(folder):
    return [name for name in os.listdir(folder) if ".tmp" in name or name.startswith(".")]


def listing(folder):
    return sorted(os.listdir(folder))


def frame_files(n=N, stem="frame"):
    return sorted(f"{stem}_{k:04d}{ext}" for k in range(n) for ext in (".exr", ".png"))


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    path = tmp_path_factory.mktemp("scene") / "anim.xml"
    path.write_text(SCENE)
    return path


@pytest.fixture(scope="module")
def reference(scene, tmp_path_factory):
    """The N frames rendered in this process (the command line), and the
    single renders at each frame's values: {"frames": folder, "single": folder}."""
    seq = tmp_path_factory.mktemp("seq")
    assert cli.main(["render", str(scene), "-o", str(seq / "frame.exr"), "--frames", str(N),
                     *SWEEP]) == 0
    single = tmp_path_factory.mktemp("single")
    for k in range(N):
        v = values(k)
        assert cli.main(["render", str(scene), "-o", str(single / f"s{k}.exr"),
                         "-D", f"angle={v['angle']}", "-D", f"R={v['R']}", "-D", "spp=3"]) == 0
    return {"frames": seq, "single": single}


def same_bytes(a, b):
    with open(a, "rb") as fa, open(b, "rb") as fb:
        return fa.read() == fb.read()


def read_png(path):
    import mitsuba as mi
    return np.array(mi.Bitmap(str(path)), dtype=np.int64)


def same_pixels(x, y, spp=3):
    """Float images x and y equal up to the order of each pixel's float32
    additions (module docstring): within (2 spp + 1) 2^-24 of their magnitude."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    bound = (2 * spp + 1) * 2.0 ** -24 * np.maximum(np.abs(x), np.abs(y))
    return x.shape == y.shape and bool(np.all(np.abs(x - y) <= bound))


def same_image(a, b, spp=3):
    """The files a and b hold the same image: byte for byte, or else EXR
    values as :func:`same_pixels`, PNG levels within 1."""
    if same_bytes(a, b):
        return True
    if str(a).endswith(".exr"):
        A, B = read_exr(a), read_exr(b)
        return A.keys() == B.keys() and all(same_pixels(A[k], B[k], spp) for k in A)
    x, y = read_png(a), read_png(b)
    return x.shape == y.shape and int(np.max(np.abs(x - y))) <= 1


def assert_same_frames(folder, ref, n=N, spp=3):
    for k in range(n):
        for ext in (".exr", ".png"):
            assert same_image(folder / f"frame_{k:04d}{ext}", ref / f"frame_{k:04d}{ext}", spp), \
                (k, ext)


@pytest.mark.timeout(120)
def test01_frames_equal_single_renders(reference):
    # Oracle: frame k (EXR and PNG) is the image of the single render with
    # frame k's values; the frames differ from each other (the sweep moves).
    seq, single = reference["frames"], reference["single"]
    assert listing(seq) == frame_files()
    for k in range(N):
        for ext in (".exr", ".png"):
            assert same_image(seq / f"frame_{k:04d}{ext}", single / f"s{k}{ext}"), (k, ext)
    rgb = [read_exr(seq / f"frame_{k:04d}.exr")["RGB"] for k in range(N)]
    assert all(img.shape == (24, 24, 3) for img in rgb)
    assert all(not np.array_equal(rgb[k], rgb[k + 1]) for k in range(N - 1))
    assert temporaries(seq) == []


def test02_sweep_values():
    # Oracle: the formula; N = 1 gives a; the last frame is b exactly;
    # fixed values stay; an <integer> parameter gets values rounded half up.
    got = frames.sweep({"a": (0.1, 0.7), "b": (10, -10)}, 4, fixed={"c": "x"})
    for k, f in enumerate(got):
        assert f["c"] == "x"
        assert f["a"] == (0.1 + (0.7 - 0.1) * k / 3 if k < 3 else 0.7)
        assert f["b"] == (10 + (-10 - 10) * k / 3 if k < 3 else -10)
    assert frames.sweep({"a": (2, 5)}, 1) == [{"a": 2.0}]
    assert frames._format(18.5, True) == "19" and frames._format(17.49, True) == "17"
    assert frames._format(0.1 + 0.2, False) == "0.30000000000000004"
    assert frames._format(3, False) == "3" and frames._format("1, 2", False) == "1, 2"


@pytest.mark.timeout(120)
def test03_integer_parameter_rounded(scene, tmp_path, capsys):
    # Oracle: -D res=16:21 over 3 frames sets the film's <integer> width and
    # height to 16, 19 (18.5 rounded half up) and 21: the EXRs' sizes.
    out = tmp_path / "f.exr"
    assert cli.main(["render", str(scene), "-o", str(out), "--frames", "3", "-D", "res=16:21",
                     "-D", "spp=1"]) == 0
    sizes = [read_exr(tmp_path / f"f_{k:04d}.exr")["RGB"].shape[:2] for k in range(3)]
    assert sizes == [(16, 16), (19, 19), (21, 21)]
    err = capsys.readouterr().err
    assert "rendered 3 of 3 frames" in err


@pytest.mark.timeout(120)
def test04_resume(scene, reference, tmp_path, capsys):
    # Oracle: with frame 2 deleted, a rerun renders frame 2 only (and says
    # so); every other file keeps its mtime (not rewritten); frame 2 is again
    # the reference frame (same_image). Then with only frame 1's PNG
    # deleted, frame 1 is rendered again (both files). A last run (through
    # the Python function) renders nothing and touches nothing.
    out = tmp_path / "frame.exr"
    args = ["render", str(scene), "-o", str(out), "--frames", str(N), *SWEEP]
    assert cli.main(args) == 0
    for frame, deleted, says in [(2, (".exr", ".png"), "rendered 1 of 4 frames"),
                                 (1, (".png",), "rendered 1 of 4 frames")]:
        for ext in deleted:
            (tmp_path / f"frame_{frame:04d}{ext}").unlink()
        old = {p.name: p.stat().st_mtime_ns for p in tmp_path.iterdir()}
        time.sleep(0.05)     # mtimes of a rewrite would differ
        capsys.readouterr()
        assert cli.main(args) == 0
        err = capsys.readouterr().err
        assert says in err and "3 already written" in err
        new = {p.name: p.stat().st_mtime_ns for p in tmp_path.iterdir()}
        assert sorted(new) == frame_files()
        changed = sorted(name for name in new if new[name] != old.get(name))
        assert changed == [f"frame_{frame:04d}.exr", f"frame_{frame:04d}.png"]
    assert_same_frames(tmp_path, reference["frames"])
    result = frames.render_frames(scene, frames.sweep({"angle": (0, 90), "R": (0.8, 1.2)}, N,
                                                      {"spp": 3}), out=out)
    assert result.rendered == [] and result.skipped == [0, 1, 2, 3]
    assert {p.name: p.stat().st_mtime_ns for p in tmp_path.iterdir()} == new
    assert temporaries(tmp_path) == []


@pytest.mark.timeout(120)
@pytest.mark.parametrize("failure", [OSError, KeyboardInterrupt])
def test05_atomic_write(scene, reference, tmp_path, monkeypatch, capsys, failure):
    # Oracle: a write that fails halfway (half the bytes written, then an
    # OSError or a Ctrl-C) while frame 1's PNG is written leaves no file
    # under frame 1's PNG name and no temporary file; frame 0 is complete and
    # frame 1's EXR (written before) is the reference. The command reports
    # the failure (exit status 2, or 130 for Ctrl-C). A rerun completes the
    # sequence: every frame the reference's image. A temporary file
    # left by a killed run is removed by the next run.
    real = render.write_bitmap

    def failing(bitmap, path):
        if ".frame_0001.png." in os.path.basename(path):
            real(bitmap, path)
            size = os.path.getsize(path)
            with open(path, "r+b") as f:
                f.truncate(size // 2)
            raise failure("disk full" if failure is OSError else "")
        real(bitmap, path)
    monkeypatch.setattr(render, "write_bitmap", failing)
    out = tmp_path / "frame.exr"
    args = ["render", str(scene), "-o", str(out), "--frames", str(N), *SWEEP]
    assert cli.main(args) == (2 if failure is OSError else 130)
    err = capsys.readouterr().err
    if failure is OSError:
        assert "lgshape: error: cannot write" in err and "frame_0001.png" in err
    assert listing(tmp_path) == ["frame_0000.exr", "frame_0000.png", "frame_0001.exr"]
    assert same_image(tmp_path / "frame_0001.exr", reference["frames"] / "frame_0001.exr")
    monkeypatch.setattr(render, "write_bitmap", real)
    stale = tmp_path / ".frame_0003.exr.k2j4h5g6.tmp.exr"
    stale.write_bytes(b"half")
    assert cli.main(args) == 0
    assert "rendered 3 of 4 frames" in capsys.readouterr().err
    assert listing(tmp_path) == frame_files()
    assert_same_frames(tmp_path, reference["frames"])


BAD = [
    # (arguments after the scene and -o, what stderr must say)
    (["-D", "angle=0:90"], ["-D angle=0:90: a range a:b is for frame sequences; "
                            "give --frames N"]),
    (["--frames", "3", "-D", "nope=0:1"], ["-D nope=0:1: the scene has no parameter 'nope'"]),
    (["--frames", "0", "-D", "angle=0:90"], ["--frames must be at least 1"]),
    (["--frames", "-2"], ["--frames must be at least 1"]),
    (["--frames", "3", "-D", "res=0:16"], ["-D res=0:16: 'res' must be at least 1", "width"]),
    (["--frames", "3", "-D", "spp=abc"], ["-D spp=abc: 'spp' must be an integer"]),
    (["--video"], ["--video is for frame sequences; give --frames N"]),
    (["--workers", "2"], ["--workers is for frame sequences; give --frames N"]),
    (["--frames", "2", "--workers", "0"], ["--workers must be at least 1"]),
    (["--frames", "2", "--video", "--fps", "0"], ["--fps must be positive"]),
]


@pytest.mark.parametrize("args, messages", BAD, ids=[" ".join(a) for a, _ in BAD])
def test06_errors(scene, tmp_path, capsys, args, messages):
    # Oracle: exit status 2, "lgshape: error:" and the message naming the
    # option or -D on stderr, no traceback, nothing written or rendered.
    def trap(*a, **k):
        raise AssertionError("rendered")
    mp = pytest.MonkeyPatch()
    mp.setattr(render, "render_passes", trap)
    try:
        assert cli.main(["render", str(scene), "-o", str(tmp_path / "f.exr"), *args]) == 2
    finally:
        mp.undo()
    err = capsys.readouterr().err
    assert err.startswith("lgshape: error:") and "Traceback" not in err, err
    for message in messages:
        assert message in err
    assert os.listdir(tmp_path) == []


def test06b_workers_and_cluster_exclusive(scene, tmp_path, capsys):
    # Oracle: argparse refuses both (exit status 2, naming both options).
    with pytest.raises(SystemExit) as exc:
        cli.main(["render", str(scene), "--frames", "2", "--workers", "2",
                  "--cluster", "tcp://127.0.0.1:8786"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "--cluster" in err and "--workers" in err


def test06c_api_errors(scene, tmp_path):
    # Oracle: the Python function refuses what the command line refuses,
    # naming the frame whose values are wrong; nothing is written.
    with pytest.raises(cli.CommandError, match="no frames"):
        frames.render_frames(scene, [], out=tmp_path / "f.exr")
    with pytest.raises(cli.CommandError, match=r"frame 1: -D res=0: 'res' must be at least 1"):
        frames.render_frames(scene, [{"res": 8}, {"res": 0}], out=tmp_path / "f.exr")
    with pytest.raises(cli.CommandError, match="frame 0: -D nope=1"):
        frames.render_frames(scene, [{"nope": 1}], out=tmp_path / "f.exr")
    assert os.listdir(tmp_path) == []


@pytest.mark.timeout(120)
def test07_python_api_list_of_dicts(scene, tmp_path):
    # Oracle: frames given as any list of dicts (numbers, strings) equal the
    # single renders at those values; -o x.png writes PNGs only.
    params = [{"angle": 10, "R": 1.1, "spp": 2}, {"angle": "45.5", "spp": 2.4}]
    result = frames.render_frames(scene, params, out=tmp_path / "p.png")
    assert result.rendered == [0, 1] and result.where == {0: "local", 1: "local"}
    assert listing(tmp_path) == ["p_0000.png", "p_0001.png"]
    for k, d in enumerate([["angle=10", "R=1.1", "spp=2"], ["angle=45.5", "spp=2"]]):
        single = tmp_path / "single" / f"s{k}.png"
        single.parent.mkdir(exist_ok=True)
        argv = ["render", str(scene), "-o", str(single)]
        for x in d:
            argv += ["-D", x]
        assert cli.main(argv) == 0
        assert same_image(tmp_path / f"p_{k:04d}.png", single, spp=2)


@pytest.mark.timeout(120)
def test08_scene_text_on_a_worker_without_the_file(scene, tmp_path):
    # Oracle: a worker that does not have the scene file at its path renders
    # the XML text sent with the task: the same image (same_pixels) as
    # loading the file.
    v = {"angle": "30.0", "R": "0.9", "spp": "2"}
    here = render.render_image(str(scene), v, progress=lambda *a: None)
    job = {"path": str(tmp_path / "elsewhere" / "anim.xml"), "text": SCENE, "spp": None,
           "variant": render.DEFAULT_VARIANT}
    there = frames.render_task(job, v)
    assert there["names"] == here["names"]
    assert same_pixels(there["image"], here["image"], spp=2)
    assert there["where"].endswith(f":{os.getpid()}")
    # Where the file at the path is not the text sent (here: another
    # scene), the text wins, and its relative file names (an <include>)
    # are resolved in the scene's folder: as loading the sent text's file.
    folder = tmp_path / "scenes"
    folder.mkdir()
    (folder / "sky.xml").write_text('<scene version="3.0.0"><emitter type="constant">'
                                    '<rgb name="radiance" value="0.2, 0.3, 0.9"/>'
                                    '</emitter></scene>')
    text = SCENE.replace('<emitter type="constant"/>', '<include filename="sky.xml"/>')
    (folder / "sent.xml").write_text(text)
    (folder / "anim.xml").write_text(SCENE)
    job.update(path=str(folder / "anim.xml"), text=text)
    there = frames.render_task(job, v)
    here = render.render_image(str(folder / "sent.xml"), v, progress=lambda *a: None)
    assert same_pixels(there["image"], here["image"], spp=2)
    plain = render.render_image(str(folder / "anim.xml"), v, progress=lambda *a: None)
    assert not np.array_equal(there["image"], plain["image"])


@pytest.mark.timeout(120)
def test09_workers_same_bits_and_video(scene, reference, tmp_path, capsys):
    # Oracle: --workers 2 (a LocalCluster of 2 worker processes, started and
    # stopped by the command) writes the in-process frames' images,
    # rendered in other processes (the per-frame lines name host:pid);
    # --video writes an MP4 that imageio-ffmpeg reads back as N frames of
    # 24x24. No worker process is left running.
    import imageio_ffmpeg
    import psutil
    out = tmp_path / "frame.exr"
    t0 = time.perf_counter()
    assert cli.main(["render", str(scene), "-o", str(out), "--frames", str(N), *SWEEP,
                     "--workers", "2", "--video", "--fps", "12"]) == 0
    seconds = time.perf_counter() - t0
    err = capsys.readouterr().err
    assert_same_frames(tmp_path, reference["frames"])
    pids = {int(m.group(1)) for m in re.finditer(r"^lgshape: frame \d+ \(.*?, [^:]+:(\d+)\)",
                                                  err, re.M)}
    assert pids and os.getpid() not in pids
    assert listing(tmp_path) == sorted(frame_files() + ["frame.mp4"])
    reader = imageio_ffmpeg.read_frames(str(tmp_path / "frame.mp4"))
    meta = next(reader)
    assert meta["size"] == (24, 24) and sum(1 for _ in reader) == N
    for pid in pids:
        assert not psutil.pid_exists(pid) or \
            psutil.Process(pid).status() == psutil.STATUS_ZOMBIE, "a worker is still running"
    print(f"--workers 2: {seconds:.1f} s")


@pytest.fixture
def local_cluster():
    from dask.distributed import Client, LocalCluster
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=None) as lc, Client(lc) as client:
        yield lc, client


@pytest.mark.timeout(120)
def test10_killed_worker(scene, tmp_path, local_cluster):
    # Oracle: a worker process killed with SIGKILL (its pid from the
    # cluster) while it renders a frame (seen executing that frame's task
    # twice, 0.2 s apart): the run completes, every frame is written once,
    # the killed frame by another process, and all frames are the images of
    # the frames rendered in this process. Frames of 48x48 at 256 spp (about
    # 1 s each here), so that one is caught running.
    cluster, client = local_cluster
    params = frames.sweep({"angle": (0, 90), "R": (0.8, 1.2)}, N, {"res": 48, "spp": 256})
    (tmp_path / "here").mkdir()
    here = frames.render_frames(scene, params, out=tmp_path / "here" / "frame.exr")
    killed, stop = {}, threading.Event()

    def executing(dask_worker):   # a local function: sent by value, nothing imported
        return [str(ts.key) for ts in dask_worker.state.executing
                if str(ts.key).startswith("lgshape-frame-")]

    def killer():
        seen = {}
        while not stop.is_set():
            try:
                running = client.run(executing)
                pids = client.run(os.getpid)
            except Exception:
                time.sleep(0.05)
                continue
            for address, keys in running.items():
                if keys and seen.get(address) == keys[0] and address in pids:
                    killed.update(pid=pids[address], key=keys[0])
                    os.kill(pids[address], signal.SIGKILL)
                    return
                seen[address] = keys[0] if keys else None
            time.sleep(0.2)

    thread = threading.Thread(target=killer, daemon=True)
    thread.start()
    t0 = time.perf_counter()
    try:
        result = frames.render_frames(scene, params, out=tmp_path / "frame.exr",
                                      cluster=cluster.scheduler_address)
    finally:
        stop.set()
        thread.join(10)
    seconds = time.perf_counter() - t0
    assert killed, "no frame was seen running"
    frame = int(killed["key"].split("-")[2])
    assert sorted(result.rendered) == list(range(N))
    assert not result.where[frame].endswith(f":{killed['pid']}")
    assert listing(tmp_path) == sorted(frame_files() + ["here"])
    assert_same_frames(tmp_path, tmp_path / "here", spp=256)
    assert here.rendered == list(range(N))
    print(f"killed worker {killed['pid']} during frame {frame}; run took {seconds:.1f} s "
          f"(in this process: {here.seconds:.1f} s); frames rendered by {result.where}")
