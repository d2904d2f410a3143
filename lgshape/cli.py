"""The ``lgshape`` command line: ``lgshape render`` renders a Mitsuba XML scene
with lgshape's plugins registered, one image or a frame sequence;
``lgshape bench`` runs the benchmark (:mod:`lgshape.bench`).

    lgshape render SCENE.xml -o OUT.exr [--spp N] [--variant V] [-D name=value ...]
    lgshape render SCENE.xml -o out/frame.exr --frames N -D name=a:b [-D name=value ...]
                   [--video [--fps F]] [--workers N | --cluster tcp://host:8786]

The image is rendered in passes of a few samples per pixel (pass i with
seed i; their sizes depend only on the sample count and the film size, not
on timings, so the same command draws the same samples), with a progress bar
on stderr, and averaged. ``-o x.exr``
writes the EXR (all channels, AOVs under their names) and ``x.png`` beside
it; ``-o x.png`` writes the PNG only. Each file is written to a temporary
file in the same folder and then renamed, so a crash leaves no half-written
image under the output's name.

``--frames N`` renders a frame sequence (:mod:`lgshape.frames`): each
``-D name=a:b`` (a and b numbers) goes linearly from a to b over the N
frames, value_k = a + (b - a) k / (N - 1) (rounded where the parameter sets an
``<integer>``); a plain ``-D name=value`` stays fixed. Frame k goes to
``out/frame_000k.exr`` (and ``.png``) and equals a single render with those
values; frames whose files all exist are skipped (resume). ``--video`` also
writes ``out/frame.mp4`` from the PNGs (ffmpeg from the imageio-ffmpeg
package). ``--workers N`` renders on a local Dask cluster of N worker
processes, ``--cluster ADDRESS`` on a running Dask cluster; without them the
frames render in this process. One progress bar covers all frames.

Bad input is reported as ``lgshape: error: ...`` on stderr with exit status 2,
before anything is rendered: the output's extension and folder (it must exist
and be writable; a file is created and removed there to find out), ``-D``
names that the scene does not use, ``-D`` values that the scene's
``<integer>``/``<float>`` cannot take or that make the film or the sample
count 0, XML and plugin errors from Mitsuba and lgsurface (without the
Python traceback that Mitsuba embeds in a plugin's error), ``-D name=a:b``
without ``--frames``, a ``--frames`` or ``--workers`` below 1, an ``--fps``
that is not positive.
"""
from __future__ import annotations

import argparse
import contextlib
import math
import os
import re
import sys
import tempfile
import time
import xml.etree.ElementTree as ET

DEFAULT_VARIANT = "llvm_ad_rgb"
#: Samples (pixels x samples per pixel) in one rendering pass, about a second
#: on 2 cores: the progress bar's step, and a bound on the wavefront's memory.
#: The passes are a function of the sample count and the film size only (not
#: of timings), so that the same command renders the same image.
PASS_SAMPLES = 1 << 20


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "bench":
        try:
            from . import bench
        except ModuleNotFoundError as err:
            if err.name != "lgshape.bench":
                raise
            print("lgshape: error: the benchmark (lgshape.bench) is not installed", file=sys.stderr)
            return 2
        return bench.main(argv[1:])
    args = _parser().parse_args(argv)
    try:
        return render(args)
    except CommandError as err:
        print(f"lgshape: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("\nlgshape: interrupted", file=sys.stderr)
        return 130


class CommandError(Exception):
    pass


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="lgshape", description="Implicit surfaces in Mitsuba 3.")
    sub = p.add_subparsers(dest="command", required=True, metavar="{render,bench}")
    r = sub.add_parser("render", help="render a Mitsuba XML scene",
                       description="Render a Mitsuba XML scene that may contain lgsurface "
                                   "shapes and lg_* integrators.")
    r.add_argument("scene", help="the scene file (Mitsuba XML)")
    r.add_argument("-o", "--output", help="output image, .exr (with a .png beside it) or "
                   ".png (default: the scene's name with .exr, in the current folder)")
    r.add_argument("--spp", type=int, help="samples per pixel (default: the scene's sampler)")
    r.add_argument("--variant", default=DEFAULT_VARIANT,
                   help=f"Mitsuba variant (default: {DEFAULT_VARIANT})")
    r.add_argument("-D", dest="defines", action="append", default=[], metavar="name=value",
                   help="set a <default> parameter of the scene, as in the mitsuba program; "
                        "with --frames, name=a:b goes linearly from a to b")
    f = r.add_argument_group("frame sequences (lgshape.frames)")
    f.add_argument("--frames", type=int, metavar="N",
                   help="render N frames, OUT_0000.exr, OUT_0001.exr, ...: each -D name=a:b "
                        "goes linearly from a to b; frames already written are skipped")
    f.add_argument("--video", action="store_true",
                   help="also write OUT.mp4 from the frames' PNGs")
    f.add_argument("--fps", type=float, default=24.0,
                   help="frame rate of the --video (default: 24)")
    where = f.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, metavar="N",
                       help="render the frames on a local Dask cluster of N worker processes")
    where.add_argument("--cluster", metavar="ADDRESS",
                       help="render the frames on the running Dask cluster at ADDRESS "
                            "(tcp://host:8786)")
    sub.add_parser("bench", help="run the benchmark (lgshape bench --help)", add_help=False)
    return p


def render(args) -> int:
    if not os.path.isfile(args.scene):
        raise CommandError(f"no such scene file: {args.scene}")
    out = args.output or os.path.splitext(os.path.basename(args.scene))[0] + ".exr"
    ext = os.path.splitext(out)[1].lower()
    if ext not in (".exr", ".png"):
        raise CommandError(f"-o {out}: the output must end in .exr or .png")
    defines = {}
    for d in args.defines:
        name, sep, value = d.partition("=")
        if not sep or not name:
            raise CommandError(f"-D expects name=value, got '{d}'")
        defines[name] = value
    if args.spp is not None and args.spp < 1:
        raise CommandError("--spp must be at least 1")
    sequence = (args.frames is not None or args.video or args.workers is not None
                or args.cluster is not None or any(_range(v) for v in defines.values()))
    if sequence:
        from . import frames
        return frames.cli_render(args, out, defines)
    _check_output(out, ext)
    _check_defines(args.scene, defines)

    result = render_image(args.scene, defines, spp=args.spp, variant=args.variant)
    import mitsuba as mi
    written = write_image(mi, result["image"], result["names"], out)
    print(f"lgshape: rendered {args.scene} ({result['size']}, {result['spp']} spp) in "
          f"{result['seconds']:.1f} s; wrote {', '.join(written)}", file=sys.stderr)
    return 0


def _range(value):
    """(a, b) for a -D value "a:b" of two finite numbers, else None."""
    a, sep, b = value.partition(":")
    if not sep:
        return None
    try:
        a, b = float(a), float(b)
    except ValueError:
        return None
    return (a, b) if math.isfinite(a) and math.isfinite(b) else None


def use_variant(variant):
    """Set the Mitsuba variant and register lgshape's plugins for it; returns
    the mitsuba module. The one set-up of a rendering process: the command
    line and the Dask workers of :mod:`lgshape.frames` go through it."""
    import mitsuba as mi
    import lgshape
    if variant not in mi.variants():
        raise CommandError(f"unknown variant '{variant}'; this Mitsuba has "
                           f"{', '.join(mi.variants())}")
    if variant.startswith("cuda_"):
        _check_cuda(variant)
    try:
        mi.set_variant(variant)
    except Exception as err:  # e.g. a cuda_ variant without a usable GPU
        raise CommandError(f"cannot use the variant '{variant}': {err}") from None
    try:
        lgshape.register_plugins()
    except RuntimeError as err:
        raise CommandError(str(err)) from None
    return mi


def _check_cuda(variant):
    """A cuda_ variant needs Dr.Jit's CUDA backend, which Dr.Jit initialises
    when it is imported if it finds a GPU: without one, say so (Mitsuba's own
    message, "the CUDA backend hasn't been initialized", comes later and
    names no cause)."""
    import drjit as dr
    if dr.has_backend(dr.JitBackend.CUDA):
        return
    import ctypes.util
    why = ("no CUDA driver (libcuda.so) is installed" if ctypes.util.find_library("cuda") is None
           else "the CUDA driver found no usable GPU")
    raise CommandError(f"cannot use the variant '{variant}': no CUDA device was found "
                       f"({why}; Dr.Jit's CUDA backend did not start). Render on the CPU "
                       f"with --variant {variant.replace('cuda_', 'llvm_', 1)}")


def render_image(scene_path, defines, spp=None, variant=DEFAULT_VARIANT, text=None,
                 progress=None, warn=None):
    """Load the scene (``mi.load_file``; with ``text``, that XML instead,
    relative file names resolved in the scene's folder) with the ``-D``
    values ``defines`` (name -> string) and render it in passes (see
    :data:`PASS_SAMPLES`). ``progress(done, spp)`` is called after each
    pass (default: a progress bar on stderr); ``warn(message)`` gets the
    warnings (default: printed on stderr). Returns a dict: ``image`` (float32
    array, height x width x channels), ``names`` (the channel names),
    ``spp``, ``size`` ("WxH") and ``seconds``. Raises :class:`CommandError`."""
    if warn is None:
        def warn(message):
            print(f"lgshape: warning: {message}", file=sys.stderr)
    mi = use_variant(variant)
    try:
        if text is None:
            scene = mi.load_file(scene_path, **defines)
        else:
            scene = _load_text(mi, text, os.path.dirname(os.path.abspath(scene_path)), defines)
    except Exception as err:  # Mitsuba reports parse and plugin errors as RuntimeError
        given = "".join(f" -D {k}={v}" for k, v in defines.items())
        raise CommandError(f"cannot load {scene_path}:\n{_clean_error(str(err))}"
                           + (f"\n(loaded with{given})" if given else "")) from None
    if not isinstance(scene, mi.Scene):
        raise CommandError(f"{scene_path} is not a scene: its root element is a "
                           f"{type(scene).__name__}, not <scene>")

    if not scene.sensors():
        raise CommandError(f"{scene_path} has no <sensor>: nothing to render")
    sensor = scene.sensors()[0]
    if scene.integrator() is None:
        raise CommandError(f"{scene_path} has no <integrator>: add e.g. "
                           "<integrator type=\"lg_path\"/>")
    # An integrator that cannot see the lgsurfaces, media the lg integrators
    # ignore (named as the scene names them): said here, once, through `warn`
    # (mi.render's own check then stays quiet).
    from lgshape.plugins.checks import NotDifferentiableError, check_render
    try:
        check_render(scene, scene.integrator(), sensor, warn=warn)
    except NotDifferentiableError as err:
        raise CommandError(str(err)) from None
    width, height = (int(v) for v in sensor.film().crop_size())
    if width < 1 or height < 1:
        raise CommandError(f"the film of {scene_path} is {width}x{height} pixels; its width "
                           "and height must be at least 1")
    spp = spp or sensor.sampler().sample_count()
    if spp < 1:
        raise CommandError(f"the sampler of {scene_path} has sample_count {spp}; give a "
                           "positive sample_count or --spp N")
    image, names, seconds = _render_passes(mi, scene, sensor, spp, progress)
    return {"image": image, "names": names, "spp": spp, "seconds": seconds,
            "size": f"{image.shape[1]}x{image.shape[0]}"}


def _load_text(mi, text, folder, defines):
    """mi.load_string with `folder` first on the file resolver, as
    mi.load_file does with the scene file's folder."""
    old = mi.file_resolver()
    resolver = mi.FileResolver(old)
    resolver.prepend(folder)
    mi.set_file_resolver(resolver)
    try:
        return mi.load_string(text, **defines)
    finally:
        mi.set_file_resolver(old)


def write_image(mi, image, names, out):
    """Write the rendered image to `out` (.exr: the EXR and the PNG beside
    it; .png: the PNG), each file atomically; returns the paths written."""
    # MultiChannel: with the inferred format, 4 channels (R, G, B and one AOV)
    # would be written as RGBA, the AOV's name lost.
    bitmap = mi.Bitmap(image, pixel_format=mi.Bitmap.PixelFormat.MultiChannel,
                       channel_names=names)
    written = []
    try:
        if os.path.splitext(out)[1].lower() == ".exr":
            _write_atomic(bitmap, out)
            written.append(out)
            out = os.path.splitext(out)[0] + ".png"
        _write_atomic(_preview(mi, bitmap), out)
    except (OSError, RuntimeError) as err:
        raise CommandError(f"cannot write {out}: {err}") from None
    written.append(out)
    return written


def _write_atomic(bitmap, path):
    """Write the bitmap to a temporary file in path's folder (named
    ``.NAME.XXXXXXXX.tmp.EXT``), then rename it to path: path is never
    half-written, and the temporary file is removed on any error."""
    folder = os.path.dirname(os.path.abspath(path))
    ext = os.path.splitext(path)[1]
    fd, tmp = tempfile.mkstemp(prefix=f".{os.path.basename(path)}.", suffix=f".tmp{ext}",
                               dir=folder)
    os.close(fd)
    try:
        os.chmod(tmp, 0o666 & ~_umask())        # mkstemp's file is 0600
        _write_bitmap(bitmap, tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        raise


def _write_bitmap(bitmap, path):
    """The one place where an image file is written."""
    bitmap.write(path)


def _read_umask():
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


_UMASK = _read_umask()      # read once: setting it races with other threads


def _umask():
    return _UMASK


def _check_output(out, ext):
    """Fail before rendering where the output cannot be written: its folder
    must exist and take a new file (one is created and removed there)."""
    folder = os.path.dirname(os.path.abspath(out))
    if not os.path.isdir(folder):
        what = "is not a folder" if os.path.exists(folder) else "does not exist"
        raise CommandError(f"-o {out}: the output folder {folder} {what}")
    paths = [out] + ([os.path.splitext(out)[0] + ".png"] if ext == ".exr" else [])
    for path in paths:
        if os.path.isdir(path):
            raise CommandError(f"-o {out}: {path} is a folder")
    try:
        fd, probe = tempfile.mkstemp(prefix=".lgshape-", suffix=ext, dir=folder)
        os.close(fd)
        os.remove(probe)
    except OSError as err:
        raise CommandError(f"-o {out}: cannot write to the output folder {folder}: "
                           f"{err.strerror or err}") from None
    for path in paths:
        if os.path.exists(path) and not os.access(path, os.W_OK):
            raise CommandError(f"-o {out}: cannot overwrite {path}: permission denied")


#: (plugin element, property) -> the least value it takes: checked for -D
#: values, as Mitsuba loads 0 and fails only when rendering.
_AT_LEAST_ONE = {("film", "width"), ("film", "height"), ("film", "crop_width"),
                 ("film", "crop_height"), ("sampler", "sample_count")}
_INTEGER = re.compile(r"\s*[+-]?\d+\s*")


def scan_scene(scene_path):
    """What the scene's XML says about its parameters: a dict with ``known``
    (the <default> names), ``uses`` (name -> [(element, whole value,
    plugin element)] for each $name), ``includes`` (whether it has an
    <include>) and ``integers`` (the names that fill a whole <integer>).
    None where the XML cannot be read (Mitsuba's loader then reports it)."""
    try:
        root = ET.parse(scene_path).getroot()
    except (ET.ParseError, OSError, ValueError):
        return None
    known, uses, includes = set(), {}, False

    def walk(elem, plugin):
        nonlocal includes
        if elem.tag == "default" and "name" in elem.attrib:
            known.add(elem.attrib["name"])
        if elem.tag == "include":
            includes = True
        for value in elem.attrib.values():
            for ref in re.findall(r"\$(\w+)", value):
                uses.setdefault(ref, []).append((elem, value == "$" + ref, plugin))
        child_plugin = elem if "type" in elem.attrib else plugin
        for child in elem:
            walk(child, child_plugin)

    walk(root, root)
    integers = {name for name, refs in uses.items()
                if any(whole and elem.tag == "integer" for elem, whole, _ in refs)}
    return {"known": known, "uses": uses, "includes": includes, "integers": integers}


def _check_defines(scene_path, defines, scan=None, shown=None):
    """Check -D against the scene's XML before Mitsuba loads it: every name
    must be a <default> or a $name of the scene, and a value that fills a
    whole <integer> or <float> must be one (at least 1 for the film size
    and the sample count). Where the XML cannot be read, Mitsuba's loader
    reports the problem. `scan`: scan_scene(scene_path), if at hand;
    `shown`: name -> the value to name in messages (default: the value)."""
    if not defines:
        return
    scan = scan_scene(scene_path) if scan is None else scan
    if scan is None:
        return
    known, uses, includes = scan["known"], scan["uses"], scan["includes"]
    names = sorted(known | set(uses))
    for name, value in defines.items():
        given = f"-D {name}={(shown or {}).get(name, value)}"
        if name not in known and name not in uses:
            if includes:
                continue  # an included file may use it: Mitsuba checks
            have = ", ".join(names) if names else "none"
            raise CommandError(f"{given}: the scene has no parameter '{name}' "
                               f"(its parameters: {have})")
        for elem, whole, plugin in uses.get(name, []):
            if not whole or elem.tag not in ("integer", "float"):
                continue
            prop = elem.attrib.get("name", "?")
            where = (f"<{elem.tag} name=\"{prop}\"> of the <{plugin.tag}"
                     + (f" type=\"{plugin.attrib['type']}\"" if "type" in plugin.attrib else "")
                     + ">")
            if elem.tag == "integer" and not _INTEGER.fullmatch(value):
                raise CommandError(f"{given}: '{name}' must be an integer "
                                   f"(it sets {where})")
            if elem.tag == "float":
                try:
                    float(value)
                except ValueError:
                    raise CommandError(f"{given}: '{name}' must be a number "
                                       f"(it sets {where})") from None
            if (plugin.tag, prop) in _AT_LEAST_ONE and float(value) < 1:
                raise CommandError(f"{given}: '{name}' must be at least 1 "
                                   f"(it sets {where})")


def _clean_error(message):
    """Mitsuba's load error without the Python traceback it embeds when a
    Python plugin (lgsurface, lg_*) raised, and without its source locations
    ('[parser.cpp:451] ')."""
    message = re.sub(r"Traceback \(most recent call last\):\n(?:[ \t].*\n)*"
                     r"(?:[\w.]+(?:Error|Exception): )?", "", message)
    message = re.sub(r"\[[\w./-]+\.(?:cpp|h|py):\d+\] ", "", message)
    return message.strip()


def pass_sizes(spp, pixels):
    """The samples per pixel of each rendering pass, a function of `spp` and
    the number of pixels only; pass i is rendered with seed i. Passes of at
    most PASS_SAMPLES samples, all of one size where a divisor of spp allows
    it (the spp of a pass is part of the render kernel: a second size would
    compile it a second time), else equal within 1."""
    per_pass = max(1, min(spp, PASS_SAMPLES // max(1, pixels)))
    divisor = max(k for k in range(1, per_pass + 1) if spp % k == 0)
    if 2 * divisor >= per_pass:
        return [divisor] * (spp // divisor)
    count = -(-spp // per_pass)
    base, extra = divmod(spp, count)
    return [base + 1] * extra + [base] * (count - extra)


def _render_passes(mi, scene, sensor, spp, progress=None):
    """Render ``spp`` samples in the passes of :func:`pass_sizes`, pass i
    with seed i; returns (image as float32 numpy array, channel names,
    seconds). ``progress(done, spp)`` after each pass (default: a progress
    bar on stderr)."""
    import numpy as np
    bar = None
    if progress is None:
        bar = _ProgressBar(spp)
        t_bar = time.perf_counter()

        def progress(done, total):
            bar.update(done, time.perf_counter() - t_bar)
    width, height = (int(v) for v in sensor.film().crop_size())
    total, done = None, 0
    t0 = time.perf_counter()
    for i, n in enumerate(pass_sizes(spp, width * height)):
        img = np.array(mi.render(scene, sensor=sensor, spp=n, seed=i), dtype=np.float64)
        total = img * n if total is None else total + img * n
        done += n
        progress(done, spp)
    if bar is not None:
        bar.close()
    names = [field.name for field in sensor.film().bitmap().struct_()]
    return (total / spp).astype(np.float32), names, time.perf_counter() - t0


def _preview(mi, bitmap):
    """An 8-bit sRGB PNG: the colour channels; when they are all zero (an AOV
    render without a nested integrator), the first AOV, scaled to [0, 1]."""
    import numpy as np
    layers = dict(bitmap.split())
    root = layers.pop("<root>", None)
    if root is None or (not np.any(np.array(root)) and layers):
        aov = np.array(next(iter(layers.values())), dtype=np.float32)
        if aov.ndim == 2:
            aov = aov[..., None]
        lo, hi = aov.min(), aov.max()
        aov = (aov - lo) / (hi - lo) if hi > lo else np.zeros_like(aov)
        rgb = np.repeat(aov[..., :1], 3, -1) if aov.shape[-1] < 3 else aov[..., :3]
        return mi.Bitmap(np.ascontiguousarray(rgb)).convert(
            mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, srgb_gamma=False)
    alpha = root.channel_count() in (2, 4)
    fmt = mi.Bitmap.PixelFormat.RGBA if alpha else mi.Bitmap.PixelFormat.RGB
    return root.convert(fmt, mi.Struct.Type.UInt8, srgb_gamma=True)


class _ProgressBar:
    """A text progress bar on stderr (redrawn in place on a terminal)."""
    WIDTH = 30

    def __init__(self, total, unit="spp", tty=None):
        self.total, self.unit = total, unit
        self.tty = sys.stderr.isatty() if tty is None else tty

    def update(self, done, elapsed):
        """`done` of the total (a float: part of a frame counts)."""
        if not self.tty:
            return
        frac = done / self.total if self.total else 1.0
        fill = int(round(frac * self.WIDTH))
        eta = elapsed / frac - elapsed if frac > 0 else math.inf
        bar = "#" * fill + "." * (self.WIDTH - fill)
        sys.stderr.write(f"\rRendering [{bar}] {100 * frac:3.0f}% {int(done)}/{self.total} "
                         f"{self.unit}, {elapsed:.1f} s, ETA {eta:.1f} s ")
        sys.stderr.flush()

    def close(self):
        if self.tty:
            sys.stderr.write("\n")


if __name__ == "__main__":
    sys.exit(main())
