"""The ``lgshape`` command line: ``lgshape render`` renders a Mitsuba XML scene
with lgshape's plugins registered; ``lgshape bench`` runs the benchmark
(:mod:`lgshape.bench`).

    lgshape render SCENE.xml -o OUT.exr [--spp N] [--variant V] [-D name=value ...]

The image is rendered in passes of a few samples per pixel, with a progress
bar on stderr, and averaged. ``-o x.exr`` writes the EXR (all channels, AOVs
under their names) and ``x.png`` beside it; ``-o x.png`` writes the PNG only.

Bad input is reported as ``lgshape: error: ...`` on stderr with exit status 2,
before anything is rendered: the output's extension and folder (it must exist
and be writable; a file is created and removed there to find out), ``-D``
names that the scene does not use, ``-D`` values that the scene's
``<integer>``/``<float>`` cannot take or that make the film or the sample
count 0, XML and plugin errors from Mitsuba and lgsurface (without the
Python traceback that Mitsuba embeds in a plugin's error).
"""
from __future__ import annotations

import argparse
import math
import os
import re
import sys
import tempfile
import time
import xml.etree.ElementTree as ET

DEFAULT_VARIANT = "llvm_ad_rgb"
PASS_SECONDS = 1.0          # aim of one rendering pass: the progress bar's step


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
                   help="set a <default> parameter of the scene, as in the mitsuba program")
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
    _check_output(out, ext)
    _check_defines(args.scene, defines)

    import mitsuba as mi
    import lgshape
    if args.variant not in mi.variants():
        raise CommandError(f"unknown variant '{args.variant}'; this Mitsuba has "
                           f"{', '.join(mi.variants())}")
    try:
        mi.set_variant(args.variant)
    except Exception as err:  # e.g. a cuda_ variant without a usable GPU
        raise CommandError(f"cannot use the variant '{args.variant}': {err}") from None
    try:
        lgshape.register_plugins()
    except RuntimeError as err:
        raise CommandError(str(err)) from None
    try:
        scene = mi.load_file(args.scene, **defines)
    except Exception as err:  # Mitsuba reports parse and plugin errors as RuntimeError
        given = "".join(f" -D {k}={v}" for k, v in defines.items())
        raise CommandError(f"cannot load {args.scene}:\n{_clean_error(str(err))}"
                           + (f"\n(loaded with{given})" if given else "")) from None
    if not isinstance(scene, mi.Scene):
        raise CommandError(f"{args.scene} is not a scene: its root element is a "
                           f"{type(scene).__name__}, not <scene>")

    from lgshape.plugins.common import lg_shapes
    integrator = scene.integrator()
    if lg_shapes(scene) and not type(integrator).__module__.startswith("lgshape.plugins"):
        print(f"lgshape: warning: the integrator {type(integrator).__name__} does not see "
              "lgsurface shapes; use lg_path, lg_direct or lg_aov", file=sys.stderr)

    if not scene.sensors():
        raise CommandError(f"{args.scene} has no <sensor>: nothing to render")
    sensor = scene.sensors()[0]
    width, height = (int(v) for v in sensor.film().crop_size())
    if width < 1 or height < 1:
        raise CommandError(f"the film of {args.scene} is {width}x{height} pixels; its width "
                           "and height must be at least 1")
    spp = args.spp or sensor.sampler().sample_count()
    if spp < 1:
        raise CommandError(f"the sampler of {args.scene} has sample_count {spp}; give a "
                           "positive sample_count or --spp N")
    image, names, seconds = _render_passes(mi, scene, sensor, spp)
    # MultiChannel: with the inferred format, 4 channels (R, G, B and one AOV)
    # would be written as RGBA, the AOV's name lost.
    bitmap = mi.Bitmap(image, pixel_format=mi.Bitmap.PixelFormat.MultiChannel,
                       channel_names=names)

    written = []
    try:
        if ext == ".exr":
            bitmap.write(out)
            written.append(out)
            out = os.path.splitext(out)[0] + ".png"
        _preview(mi, bitmap).write(out)
    except (OSError, RuntimeError) as err:
        raise CommandError(f"cannot write {out}: {err}") from None
    written.append(out)
    size = f"{image.shape[1]}x{image.shape[0]}"
    print(f"lgshape: rendered {args.scene} ({size}, {spp} spp) in {seconds:.1f} s; "
          f"wrote {', '.join(written)}", file=sys.stderr)
    return 0


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


def _check_defines(scene_path, defines):
    """Check -D against the scene's XML before Mitsuba loads it: every name
    must be a <default> or a $name of the scene, and a value that fills a
    whole <integer> or <float> must be one (at least 1 for the film size
    and the sample count). Where the XML cannot be read, Mitsuba's loader
    reports the problem."""
    if not defines:
        return
    try:
        root = ET.parse(scene_path).getroot()
    except (ET.ParseError, OSError, ValueError):
        return
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
    names = sorted(known | set(uses))
    for name, value in defines.items():
        if name not in known and name not in uses:
            if includes:
                continue  # an included file may use it: Mitsuba checks
            have = ", ".join(names) if names else "none"
            raise CommandError(f"-D {name}={value}: the scene has no parameter '{name}' "
                               f"(its parameters: {have})")
        for elem, whole, plugin in uses.get(name, []):
            if not whole or elem.tag not in ("integer", "float"):
                continue
            prop = elem.attrib.get("name", "?")
            where = (f"<{elem.tag} name=\"{prop}\"> of the <{plugin.tag}"
                     + (f" type=\"{plugin.attrib['type']}\"" if "type" in plugin.attrib else "")
                     + ">")
            if elem.tag == "integer" and not _INTEGER.fullmatch(value):
                raise CommandError(f"-D {name}={value}: '{name}' must be an integer "
                                   f"(it sets {where})")
            if elem.tag == "float":
                try:
                    float(value)
                except ValueError:
                    raise CommandError(f"-D {name}={value}: '{name}' must be a number "
                                       f"(it sets {where})") from None
            if (plugin.tag, prop) in _AT_LEAST_ONE and float(value) < 1:
                raise CommandError(f"-D {name}={value}: '{name}' must be at least 1 "
                                   f"(it sets {where})")


def _clean_error(message):
    """Mitsuba's load error without the Python traceback it embeds when a
    Python plugin (lgsurface, lg_*) raised, and without its source locations
    ('[parser.cpp:451] ')."""
    message = re.sub(r"Traceback \(most recent call last\):\n(?:[ \t].*\n)*"
                     r"(?:[\w.]+(?:Error|Exception): )?", "", message)
    message = re.sub(r"\[[\w./-]+\.(?:cpp|h|py):\d+\] ", "", message)
    return message.strip()


def _render_passes(mi, scene, sensor, spp):
    """Render ``spp`` samples in passes of about PASS_SECONDS each; returns
    (image as float32 numpy array, channel names, seconds)."""
    import numpy as np
    bar = _ProgressBar(spp)
    total, done, i, chunk = None, 0, 0, max(1, min(spp, 4))
    t0 = time.perf_counter()
    while done < spp:
        left = spp - done
        n = -(-left // -(-left // chunk))         # equal passes, no tiny last one
        t = time.perf_counter()
        img = np.array(mi.render(scene, sensor=sensor, spp=n, seed=i), dtype=np.float64)
        dt = time.perf_counter() - t
        total = img * n if total is None else total + img * n
        done, i = done + n, i + 1
        bar.update(done, time.perf_counter() - t0)
        # Next pass: about PASS_SECONDS long, growing at most 4x.
        chunk = max(1, min(4 * n, int(n * PASS_SECONDS / max(dt, 1e-3))))
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

    def __init__(self, total):
        self.total, self.tty = total, sys.stderr.isatty()

    def update(self, done, elapsed):
        if not self.tty:
            return
        frac = done / self.total
        fill = int(round(frac * self.WIDTH))
        eta = elapsed / frac - elapsed if frac > 0 else math.inf
        bar = "#" * fill + "." * (self.WIDTH - fill)
        sys.stderr.write(f"\rRendering [{bar}] {100 * frac:3.0f}% {done}/{self.total} spp, "
                         f"{elapsed:.1f} s, ETA {eta:.1f} s ")
        sys.stderr.flush()

    def close(self):
        if self.tty:
            sys.stderr.write("\n")


if __name__ == "__main__":
    sys.exit(main())
