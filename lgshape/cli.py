"""The ``lgshape`` command line: ``lgshape render`` renders a Mitsuba XML scene
with lgshape's plugins registered; ``lgshape bench`` runs the benchmark
(:mod:`lgshape.bench`).

    lgshape render SCENE.xml -o OUT.exr [--spp N] [--variant V] [-D name=value ...]

The image is rendered in passes of a few samples per pixel, with a progress
bar on stderr, and averaged. ``-o x.exr`` writes the EXR (all channels, AOVs
under their names) and ``x.png`` beside it; ``-o x.png`` writes the PNG only.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time

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
        raise CommandError(f"the output must end in .exr or .png, got '{out}'")
    defines = {}
    for d in args.defines:
        name, sep, value = d.partition("=")
        if not sep or not name:
            raise CommandError(f"-D expects name=value, got '{d}'")
        defines[name] = value
    if args.spp is not None and args.spp < 1:
        raise CommandError("--spp must be at least 1")

    import mitsuba as mi
    import lgshape
    if args.variant not in mi.variants():
        raise CommandError(f"unknown variant '{args.variant}'; this Mitsuba has "
                           f"{', '.join(mi.variants())}")
    mi.set_variant(args.variant)
    try:
        lgshape.register_plugins()
    except RuntimeError as err:
        raise CommandError(str(err)) from None
    try:
        scene = mi.load_file(args.scene, **defines)
    except Exception as err:  # Mitsuba reports parse and plugin errors as RuntimeError
        raise CommandError(f"cannot load {args.scene}:\n{err}") from None

    from lgshape.plugins.common import lg_shapes
    integrator = scene.integrator()
    if lg_shapes(scene) and not type(integrator).__module__.startswith("lgshape.plugins"):
        print(f"lgshape: warning: the integrator {type(integrator).__name__} does not see "
              "lgsurface shapes; use lg_path, lg_direct or lg_aov", file=sys.stderr)

    sensor = scene.sensors()[0]
    spp = args.spp or sensor.sampler().sample_count()
    image, names, seconds = _render_passes(mi, scene, sensor, spp)
    bitmap = mi.Bitmap(image, channel_names=names)

    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    written = []
    if ext == ".exr":
        bitmap.write(out)
        written.append(out)
        out = os.path.splitext(out)[0] + ".png"
    _preview(mi, bitmap).write(out)
    written.append(out)
    size = f"{image.shape[1]}x{image.shape[0]}"
    print(f"lgshape: rendered {args.scene} ({size}, {spp} spp) in {seconds:.1f} s; "
          f"wrote {', '.join(written)}", file=sys.stderr)
    return 0


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
