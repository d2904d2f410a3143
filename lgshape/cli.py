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
that is not positive. lgshape's warnings (an lgsurface with nothing to hit,
an integrator that cannot see lgsurfaces) are printed as
``lgshape: warning: ...`` on stderr.
"""
from __future__ import annotations

import argparse
import os
import sys
import warnings

from .plugins import VariantError
from .render import (DEFAULT_VARIANT, CommandError, check_defines, check_output,
                     parse_range, render_image, write_image)



def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "bench":
        try:
            from . import bench         # (late: the benchmark's extra, on use)
        except ModuleNotFoundError as err:
            if err.name != "lgshape.bench":
                raise
            print("lgshape: error: the benchmark (lgshape.bench) is not installed", file=sys.stderr)
            return 2
        return bench.main(argv[1:])
    args = _parser().parse_args(argv)
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _showing(warnings.showwarning)
            return render(args)
    except (CommandError, VariantError) as err:
        print(f"lgshape: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("\nlgshape: interrupted", file=sys.stderr)
        return 130


def _showing(others):
    """A ``warnings.showwarning`` that prints lgshape's warnings as the
    command's own lines and passes the others to ``others``."""
    def show(message, category, filename, lineno, file=None, line=None):
        if category.__module__.startswith("lgshape"):
            print(f"lgshape: warning: {message}", file=sys.stderr)
        else:
            others(message, category, filename, lineno, file, line)
    return show


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
                or args.cluster is not None or any(parse_range(v) for v in defines.values()))
    if sequence:
        from . import frames            # (late: sequences only)
        return frames.cli_render(args, out, defines)
    check_output(out, ext)
    check_defines(args.scene, defines)

    result = render_image(args.scene, defines, spp=args.spp, variant=args.variant)
    import mitsuba as mi
    written = write_image(mi, result["image"], result["names"], out)
    print(f"lgshape: rendered {args.scene} ({result['size']}, {result['spp']} spp) in "
          f"{result['seconds']:.1f} s; wrote {', '.join(written)}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
