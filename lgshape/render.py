"""Rendering one image from a Mitsuba XML scene, shared by the command line
(:mod:`lgshape.cli`) and frame sequences (:mod:`lgshape.frames`): checking
``-D`` values and output paths before anything renders, loading the scene
with lgshape's plugins, rendering in passes with a progress bar, and writing
EXR/PNG files atomically. Bad input raises :class:`CommandError`.
"""
from __future__ import annotations

import contextlib
import math
import os
import re
import sys
import tempfile
import time
import xml.etree.ElementTree as ET

import numpy as np

from .plugins import VariantError, use_variant

DEFAULT_VARIANT = "llvm_ad_rgb"
#: Samples (pixels x samples per pixel) in one rendering pass, about a second
#: on 2 cores: the progress bar's step, and a bound on the wavefront's memory.
#: The passes are a function of the sample count and the film size only (not
#: of timings), so that the same command renders the same image.
PASS_SAMPLES = 1 << 20


class CommandError(Exception):
    """Bad input to a render (a scene, a -D value, an output path, a variant)."""


def parse_range(value):
    """(a, b) for a -D value "a:b" of two finite numbers, else None."""
    a, sep, b = value.partition(":")
    if not sep:
        return None
    try:
        a, b = float(a), float(b)
    except ValueError:
        return None
    return (a, b) if math.isfinite(a) and math.isfinite(b) else None


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
    try:
        mi = use_variant(variant)
    except VariantError as err:
        raise CommandError(str(err)) from None
    try:
        if text is None:
            scene = mi.load_file(scene_path, **defines)
        else:
            scene = load_text(mi, text, os.path.dirname(os.path.abspath(scene_path)), defines)
    except Exception as err:  # Mitsuba reports parse and plugin errors as RuntimeError
        given = "".join(f" -D {k}={v}" for k, v in defines.items())
        raise CommandError(f"cannot load {scene_path}:\n{clean_error(str(err))}"
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
    image, names, seconds = render_passes(mi, scene, sensor, spp, progress)
    return {"image": image, "names": names, "spp": spp, "seconds": seconds,
            "size": f"{image.shape[1]}x{image.shape[0]}"}


def load_text(mi, text, folder, defines):
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
            write_atomic(bitmap, out)
            written.append(out)
            out = os.path.splitext(out)[0] + ".png"
        write_atomic(preview(mi, bitmap), out)
    except (OSError, RuntimeError) as err:
        raise CommandError(f"cannot write {out}: {err}") from None
    written.append(out)
    return written


def write_atomic(bitmap, path):
    """Write the bitmap to a temporary file in path's folder (named
    ``.NAME.XXXXXXXX.tmp.EXT``), then rename it to path: path is never
    half-written, and the temporary file is removed on any error."""
    folder = os.path.dirname(os.path.abspath(path))
    ext = os.path.splitext(path)[1]
    fd, tmp = tempfile.mkstemp(prefix=f".{os.path.basename(path)}.", suffix=f".tmp{ext}",
                               dir=folder)
    os.close(fd)
    try:
        os.chmod(tmp, 0o666 & ~umask())        # mkstemp's file is 0600
        write_bitmap(bitmap, tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        raise


def write_bitmap(bitmap, path):
    """The one place where an image file is written."""
    bitmap.write(path)


def _read_umask():
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


_UMASK = _read_umask()      # read once: setting it races with other threads


def umask():
    return _UMASK


def check_output(out, ext):
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


def check_defines(scene_path, defines, scan=None, shown=None):
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


def clean_error(message):
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


def render_passes(mi, scene, sensor, spp, progress=None):
    """Render ``spp`` samples in the passes of :func:`pass_sizes`, pass i
    with seed i; returns (image as float32 numpy array, channel names,
    seconds). ``progress(done, spp)`` after each pass (default: a progress
    bar on stderr)."""
    bar = None
    if progress is None:
        bar = ProgressBar(spp)
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
    # (an AOV integrator without a nested one returns its AOVs alone: the
    # film's last channels)
    names = names[len(names) - total.shape[2]:]
    return (total / spp).astype(np.float32), names, time.perf_counter() - t0


def preview(mi, bitmap):
    """An 8-bit sRGB PNG: the colour channels; where there are none or they
    are all zero (an AOV render without a nested integrator), the first AOV,
    scaled to [0, 1]."""
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


class ProgressBar:
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

