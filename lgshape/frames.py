"""Frame sequences: one scene rendered with a list of ``<default>`` values,
frame k to ``OUT_000k.exr`` (and ``.png``), in this process or on a Dask
cluster, resumable, optionally made into a video.

    from lgshape.frames import render_frames, sweep

    frames = sweep({"angle": (0, 90)}, 4)        # angle 0, 30, 60, 90
    render_frames("scenes/spikes.xml", frames, out="out/frame.exr", spp=16)
    render_frames("scenes/spikes.xml", frames, out="out/frame.exr", workers=2)
    render_frames("scenes/spikes.xml", frames, out="out/frame.exr",
                  cluster="tcp://host:8786", video=True)

``lgshape render SCENE -o out/frame.exr --frames N -D name=a:b ...`` calls
:func:`render_frames` with ``sweep(...)``.

Guarantees:

- **Same image as one render.** Frame k is ``lgshape render SCENE -o ...
  -D name=value ...`` with frame k's values, bit for bit (same passes, same
  seeds: :func:`lgshape.render.render_image` renders both), wherever it ran. As
  for any Mitsuba render, that holds where Mitsuba's image is itself
  reproducible: with the default Gaussian reconstruction filter, each
  sample is added into several pixels with atomic adds from Dr.Jit's
  threads, so the order of those additions, and with it the last bit of
  some pixels (about 1e-7 relative), can vary between any two renders of a
  scene, even two ``lgshape render`` runs of one command (measured here from
  32x24 pixels at 2 spp on). A ``box`` filter (``<rfilter type="box"/>``)
  adds each sample to one pixel, so a pixel's samples are summed in one
  thread's order, unless Dr.Jit's threads split them between two blocks of
  lanes (more threads make smaller blocks): on 2 cores the frames of the
  tests are identical byte for byte; with 16 threads 1 or 2 values in 1728
  differed by an ulp between two renders.
- **Resume.** A frame whose files (EXR and PNG, or the PNG for ``-o
  x.png``) all exist is skipped, whatever values made it: delete the frames
  to render again after changing the parameters.
- **Atomic files.** Each file is written to a temporary file in the same
  folder (``.frame_0003.exr.XXXXXXXX.tmp.exr``), then renamed: a crash or a
  Ctrl-C never leaves a half-written frame under its name. Temporary files
  of the sequence left by a killed run are removed by the next run.
- **On a cluster** (``workers=N``: a ``dask.distributed.LocalCluster`` of N
  worker processes that take one frame at a time, each frame rendered with
  all of Dr.Jit's threads, started and stopped here;
  ``cluster="tcp://host:8786"``: a running cluster), each frame is one Dask
  task: a worker sets the variant, registers lgshape's plugins, loads the
  scene and renders it exactly as this process would, and sends back the
  image array; this process (the driver) alone writes the files, as the
  results come in, so no frame is written twice. Tasks of a worker that
  dies are rerun by Dask on another worker (up to the scheduler's
  ``distributed.scheduler.allowed-failures``, 3 by default); ``retries``
  reruns a task that raised.
- **Scene files on a cluster.** The driver sends the scene's XML text and
  absolute path with each task. A worker that has the same file at that path
  loads it; otherwise it loads the text, with relative file names (meshes,
  textures, ``<include>``) resolved in the scene's folder, so the files a
  scene refers to must be at the same absolute path on the workers (a shared
  file system, as render farms have, or a copy).
"""
from __future__ import annotations

import contextlib
import math
import numbers
import os
import re
import socket
import subprocess
import sys
import tempfile
import time
import uuid
from dataclasses import dataclass, field

from .render import (DEFAULT_VARIANT, CommandError, ProgressBar, check_defines, check_output,
                     parse_range, render_image, scan_scene, umask, write_image)

__all__ = ["FramesResult", "frame_paths", "render_frames", "sweep", "write_video"]


@dataclass
class FramesResult:
    """What :func:`render_frames` did."""
    files: list            #: the files of each frame (its EXR and PNG, or its PNG)
    rendered: list         #: the frames rendered by this call, in the order they were written
    skipped: list          #: the frames found already written
    where: dict = field(default_factory=dict)   #: frame -> "local" or "host:pid" of its worker
    video: str | None = None                     #: the video written, if any
    seconds: float = 0.0
    size: str | None = None                      #: "WxH" of the last frame rendered
    spp: int | None = None


def sweep(ranges, count, fixed=None):
    """The parameters of `count` frames: each ``name: (a, b)`` of `ranges`
    goes linearly, a + (b - a) k / (count - 1) for frame k (the last frame
    is b exactly; one frame: a), as floats; `fixed` (name -> value) is the
    same in every frame. Integer parameters of the scene are rounded by
    :func:`render_frames`."""
    if count < 1:
        raise CommandError("--frames must be at least 1")
    frames = []
    for k in range(count):
        values = dict(fixed or {})
        for name, (a, b) in ranges.items():
            a, b = float(a), float(b)
            if count == 1:
                values[name] = a
            elif k == count - 1:
                values[name] = b
            else:
                values[name] = a + (b - a) * k / (count - 1)
        frames.append(values)
    return frames


def frame_paths(out, count):
    """The files of each of `count` frames for the output `out`: out/frame.exr
    -> [[out/frame_0000.exr, out/frame_0000.png], ...]; four digits or more."""
    stem, ext = os.path.splitext(out)
    digits = max(4, len(str(count - 1)))
    exts = [ext, ".png"] if ext.lower() == ".exr" else [ext]
    return [[f"{stem}_{k:0{digits}d}{e}" for e in exts] for k in range(count)]


def _format(value, integer):
    """A parameter value as the string Mitsuba is given: strings as they
    are; numbers of an <integer> parameter rounded (halves up); other floats
    with repr (which reads back as the same float)."""
    if isinstance(value, str):
        return value
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, numbers.Integral):
        return str(int(value))
    if isinstance(value, numbers.Real):
        value = float(value)
        if not math.isfinite(value):
            raise CommandError(f"the value {value} is not a finite number")
        return str(math.floor(value + 0.5)) if integer else repr(value)
    raise CommandError(f"a parameter value must be a string or a number, not {value!r}")


def render_frames(scene, frames, out="frame.exr", *, spp=None, variant=DEFAULT_VARIANT,
                  workers=None, cluster=None, video=False, fps=24.0, retries=1,
                  progress=None, log=None) -> FramesResult:
    """Render the scene file `scene` once per dict of `frames` (parameter
    name -> value: the scene's ``<default>``s, as ``-D``; numbers are
    rounded for a parameter that sets an ``<integer>``), frame k to
    ``frame_paths(out, len(frames))[k]``. Frames whose files all exist are
    skipped.

    `spp`: samples per pixel (default: the scene's sampler); `variant`: the
    Mitsuba variant. `workers=N`: render on a local Dask cluster of N worker
    processes (started and stopped here); `cluster`: the address of a running
    Dask scheduler (``tcp://host:8786``); neither: in this process. `video`:
    also write ``OUT.mp4`` (the stem of `out`) from the PNGs at `fps` frames
    per second. `retries`: how often Dask reruns a frame whose task raised.
    `progress`: a progress bar over all frames on stderr (default: where
    stderr is a terminal); `log(message)`: called once per frame written.

    Raises :class:`lgshape.render.CommandError` for bad input (checked before
    anything is rendered: the scene, the output folder, every frame's values
    against the scene), a scene that fails to load or render (naming the
    frame), a cluster that cannot be reached."""
    t0 = time.perf_counter()
    scene, out = os.fspath(scene), os.fspath(out)
    if not os.path.isfile(scene):
        raise CommandError(f"no such scene file: {scene}")
    ext = os.path.splitext(out)[1].lower()
    if ext not in (".exr", ".png"):
        raise CommandError(f"-o {out}: the output must end in .exr or .png")
    frames = list(frames)
    if not frames:
        raise CommandError("no frames to render")
    if spp is not None and spp < 1:
        raise CommandError("--spp must be at least 1")
    if workers is not None and cluster is not None:
        raise CommandError("give --workers or --cluster, not both")
    if workers is not None and workers < 1:
        raise CommandError("--workers must be at least 1")
    if video and not fps > 0:
        raise CommandError("--fps must be positive")

    scan = scan_scene(scene)
    integers = scan["integers"] if scan else set()
    params = []
    for k, values in enumerate(frames):
        formatted = {str(name): _format(value, name in integers) for name, value in values.items()}
        try:
            check_defines(scene, formatted, scan)
        except CommandError as err:
            raise CommandError(f"frame {k}: {err}") from None
        params.append(formatted)
    files = frame_paths(out, len(params))
    check_output(out, ext)
    for path in (p for paths in files for p in paths):
        if os.path.isdir(path):
            raise CommandError(f"-o {out}: {path} is a folder")
    _remove_stale_temporaries([p for paths in files for p in paths]
                              + [os.path.splitext(out)[0] + ".mp4"])

    done = [all(os.path.isfile(p) for p in paths) for paths in files]
    todo = [k for k in range(len(files)) if not done[k]]
    result = FramesResult(files=files, rendered=[], skipped=[k for k in range(len(files))
                                                             if done[k]])
    if todo:
        tty = sys.stderr.isatty() if progress is None else bool(progress)
        bar = ProgressBar(len(todo), unit="frames", tty=tty)
        if workers is None and cluster is None:
            _render_here(scene, params, files, todo, spp, variant, bar, result, log)
        else:
            _render_on_cluster(scene, params, files, todo, spp, variant, workers, cluster,
                               retries, bar, result, log)
        bar.close()
    if video:
        result.video = write_video(out, len(files), fps)
    result.seconds = time.perf_counter() - t0
    return result


def _render_here(scene, params, files, todo, spp, variant, bar, result, log):
    t0 = time.perf_counter()
    warned = set()

    def warn(message):
        if message not in warned:
            warned.add(message)
            print(f"lgshape: warning: {message}", file=sys.stderr)

    for i, k in enumerate(todo):
        def progress(done, total, i=i):
            bar.update(i + done / total, time.perf_counter() - t0)
        try:
            image = render_image(scene, params[k], spp=spp, variant=variant, progress=progress,
                                 warn=warn)
        except CommandError as err:
            raise CommandError(f"frame {k}: {err}") from None
        _write_frame(image, files, k, "local", result, log)
        bar.update(i + 1, time.perf_counter() - t0)


def _write_frame(image, files, k, where, result, log):
    import mitsuba as mi
    write_image(mi, image["image"], image["names"], files[k][0])
    result.rendered.append(k)
    result.where[k] = where
    result.size, result.spp = image["size"], image["spp"]
    if log is not None:
        log(f"frame {k} ({image['seconds']:.1f} s, {where}): {', '.join(files[k])}")


def _dask():
    try:
        from dask.distributed import Client, LocalCluster, as_completed
    except ImportError:
        raise CommandError("--workers and --cluster need Dask, lgshape's 'frames' extra: "
                           "pip install 'lgshape[frames]'") from None
    return Client, LocalCluster, as_completed


def _render_on_cluster(scene, params, files, todo, spp, variant, workers, cluster, retries,
                       bar, result, log):
    Client, LocalCluster, as_completed = _dask()
    local = None
    if cluster is not None:
        try:
            client = Client(cluster, timeout="20s")
        except (OSError, TimeoutError, ValueError) as err:
            raise CommandError(f"--cluster {cluster}: cannot reach a Dask scheduler there "
                               f"({err})") from None
    else:
        local = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                             dashboard_address=None)
    futures = {}
    try:
        if local is not None:
            client = Client(local)
        from ._dask import WarmUp          # (late: needs the 'frames' extra)
        client.register_plugin(WarmUp(variant))
        with open(scene, encoding="utf-8") as f:
            job = {"path": os.path.abspath(scene), "text": f.read(), "spp": spp,
                   "variant": variant}
        tag = uuid.uuid4().hex[:8]
        digits = max(4, len(str(len(files) - 1)))
        for k in todo:   # submitted in order: Dask runs earlier frames first
            future = client.submit(render_task, job, params[k], retries=retries,
                                   key=f"lgshape-frame-{k:0{digits}d}-{tag}")
            futures[future] = k
        t0 = time.perf_counter()
        warned = set()
        for done, future in enumerate(as_completed(list(futures)), 1):
            k = futures.pop(future)
            try:
                image = future.result()
            except CommandError as err:
                raise CommandError(f"frame {k}: {err}") from None
            except Exception as err:  # KilledWorker, a worker without lgshape, ...
                raise CommandError(f"frame {k} failed on the cluster: "
                                   f"{type(err).__name__}: {err}") from None
            del future
            for message in image.pop("warnings"):
                if message not in warned:
                    warned.add(message)
                    print(f"lgshape: warning: {message}", file=sys.stderr)
            _write_frame(image, files, k, image["where"], result, log)
            bar.update(done, time.perf_counter() - t0)
    finally:
        with contextlib.suppress(Exception):
            if futures:
                client.cancel(list(futures))
        with contextlib.suppress(Exception):
            client.close()
        if local is not None:
            local.close()


def render_task(job, defines):
    """One frame on a Dask worker: the same set-up and rendering as in
    the driver (:func:`lgshape.render.render_image`); returns the image array and
    its channel names, not a file."""
    path, text = job["path"], job["text"]
    try:
        with open(path, encoding="utf-8") as f:
            same = f.read() == text
    except (OSError, UnicodeDecodeError):
        same = False
    warnings = []
    image = render_image(path, defines, spp=job["spp"], variant=job["variant"],
                         text=None if same else text, progress=lambda done, total: None,
                         warn=warnings.append)
    image["warnings"] = warnings
    image["where"] = f"{socket.gethostname()}:{os.getpid()}"
    return image


_TEMPORARY = re.compile(r"\.(?P<base>.+)\.\w{8}\.tmp\.(?:exr|png|mp4)")


def _remove_stale_temporaries(files):
    """Remove the temporary files (``.NAME.XXXXXXXX.tmp.EXT``) that a killed
    run left for these files (frames, and the video)."""
    names = {}
    for path in files:
        folder, base = os.path.split(os.path.abspath(path))
        names.setdefault(folder, set()).add(base)
    pattern = _TEMPORARY
    for folder, bases in names.items():
        with contextlib.suppress(OSError):
            for entry in os.listdir(folder):
                m = pattern.fullmatch(entry)
                if m and m.group("base") in bases:
                    with contextlib.suppress(OSError):
                        os.remove(os.path.join(folder, entry))


def write_video(out, count, fps=24.0):
    """Encode the PNGs of the `count` frames of ``render_frames(...,
    out=out)`` as an H.264 MP4 (yuv420p, odd sizes padded by a pixel) at
    `fps` frames per second, to ``OUT.mp4`` (the stem of `out`), atomically,
    with the ffmpeg binary of the imageio-ffmpeg package; returns its path."""
    try:
        import imageio_ffmpeg              # (late: the 'video' extra)
    except ImportError:
        raise CommandError("--video needs imageio-ffmpeg, lgshape's 'video' extra: "
                           "pip install 'lgshape[video]'") from None
    path = os.path.splitext(out)[0] + ".mp4"
    pngs = [paths[-1] for paths in frame_paths(out, count)]
    missing = [p for p in pngs if not os.path.isfile(p)]
    if missing:
        raise CommandError(f"cannot write {path}: {missing[0]} is missing")
    stem = os.path.splitext(out)[0].replace("%", "%%")
    pattern = f"{stem}_%0{max(4, len(str(count - 1)))}d.png"
    fd, tmp = tempfile.mkstemp(prefix=f".{os.path.basename(path)}.", suffix=".tmp.mp4",
                               dir=os.path.dirname(os.path.abspath(path)))
    os.close(fd)
    cmd = [imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-loglevel", "error",
           "-framerate", repr(float(fps)), "-start_number", "0", "-i", pattern,
           "-frames:v", str(count), "-vf", "pad=ceil(iw/2)*2:ceil(ih/2)*2",
           "-c:v", "libx264", "-pix_fmt", "yuv420p", "-f", "mp4", tmp]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode != 0:
            last = proc.stderr.strip().splitlines()[-1:] or [f"exit status {proc.returncode}"]
            raise CommandError(f"cannot write {path}: ffmpeg failed: {last[0]}")
        os.chmod(tmp, 0o666 & ~umask())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        raise
    return path


def cli_render(args, out, defines) -> int:
    """``lgshape render`` with --frames, --video, --workers, --cluster or a
    -D name=a:b (from :func:`lgshape.cli.render`)."""
    ranges = {name: parse_range(value) for name, value in defines.items() if parse_range(value)}
    if args.frames is None:
        if ranges:
            name = next(iter(ranges))
            raise CommandError(f"-D {name}={defines[name]}: a range a:b is for frame "
                               "sequences; give --frames N")
        flag = ("--video" if args.video else "--workers" if args.workers is not None
                else "--cluster")
        raise CommandError(f"{flag} is for frame sequences; give --frames N")
    if args.frames < 1:
        raise CommandError("--frames must be at least 1")
    if args.workers is not None and args.workers < 1:
        raise CommandError("--workers must be at least 1")
    if args.video and not args.fps > 0:
        raise CommandError("--fps must be positive")
    fixed = {name: value for name, value in defines.items() if name not in ranges}
    # The ranges' names and ends, named as given (-D angle=0:90) in messages.
    scan = scan_scene(args.scene)
    integers = scan["integers"] if scan else set()
    ends = [{**fixed, **{n: _format(r[i], n in integers) for n, r in ranges.items()}}
            for i in (0, 1)]
    shown = {name: defines[name] for name in ranges}
    for values in ends:
        check_defines(args.scene, values, scan, shown)

    def log(message):   # a line per frame where no progress bar is drawn
        print(f"lgshape: {message}", file=sys.stderr)
    result = render_frames(args.scene, sweep(ranges, args.frames, fixed), out=out,
                           spp=args.spp, variant=args.variant, workers=args.workers,
                           cluster=args.cluster, video=args.video, fps=args.fps,
                           log=None if sys.stderr.isatty() else log)
    n, first, last = len(result.files), result.files[0][0], result.files[-1][-1]
    what = (f"rendered {len(result.rendered)} of {n} frames of {args.scene}"
            + (f" ({result.size}, {result.spp} spp)" if result.rendered else "")
            + (f", {len(result.skipped)} already written" if result.skipped else "")
            + f" in {result.seconds:.1f} s; frames {first} .. {last}")
    if result.video:
        what += f"; video {result.video}"
    print(f"lgshape: {what}", file=sys.stderr)
    return 0
