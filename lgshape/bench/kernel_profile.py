"""Where lgshape's ray kernel spends its cycles, instruction by instruction.

Samples the CPU (``perf record``, Linux) while a child process traces the
same rays through one library surface again and again on the LLVM backend;
the child then copies the code of Dr.Jit's kernels (the process's anonymous
executable mappings) to files. The samples that fall in the kernel with the
most of them are attributed to its machine instructions (``objdump``), to
its loops (a backward jump closes one) and to the straight stretches
between loop boundaries; each stretch is listed with its share, its
instruction count, its float64 (``pd``) and float32 (``ps``) vector
floating-point instructions and its gathers.

In the search's kernel the loops come in code order: the first walk (the
DDA of ``lgshape.grid.Walker.next``), the search loop (``lgshape_search``,
which holds the walk's DDA again), then the refinement loop. A sample lands
on the instruction after the one that stalls (a gather's wait shows on the
next instruction).

The "kernel" is the anonymous executable mapping with the most samples;
Linux merges neighbouring mappings of the same permissions, so it may hold
more than one kernel. perf also samples the child's start (imports, the
compile of its first traces), which falls outside the kernel.

Run: python -m lgshape.bench.kernel_profile gyroid [--rays incoherent|shadow] [--seconds 8]
(Linux on x86-64; needs ``perf``, permission to use it, and ``objdump``;
the cores should be quiet). Dr.Jit and Mitsuba are imported by the child
alone.
"""
import argparse
import collections
import ctypes
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

from ..camera import primary_rays
from ..surfaces import LIBRARY
from ..trace import Surface
from .common import VARIANT, Rays
from .speed import incoherent_rays, shadow_rays


def child(args):
    import drjit as dr
    import mitsuba as mi
    mi.set_variant(VARIANT)
    spec = LIBRARY[args.surface]()
    surf = Surface(spec)
    t_max, any_hit = float("inf"), False
    if args.rays == "incoherent":
        o, d = incoherent_rays(spec, args.res * args.res)
    else:
        o, d = primary_rays(spec.bbox, args.res)
    if args.rays == "shadow":           # the bench's: from the camera's hits to a light
        C = Rays(o, d)
        cam = surf.trace(C.o_dr, C.d_dr)
        o, d, dist, _ = shadow_rays(spec, surf, o, d, np.asarray(cam.t64), np.asarray(cam.hit))
        t_max, any_hit = mi.Float(dist), True
    R = Rays(o, d)

    def run():
        r = surf.trace(R.o_dr, R.d_dr, t_max=t_max, any_hit=any_hit)
        dr.eval(r.hit, r.t)
        dr.sync_thread()
    for _ in range(3):                  # compile, record the frozen function
        run()
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < args.seconds:
        run()
    with open(os.path.join(args.out, "maps.txt"), "w") as maps:
        k = 0
        for line in open("/proc/self/maps"):
            parts = line.split()
            # anonymous (no path: five fields), readable and executable
            if parts[1][0] == "r" and parts[1][2] == "x" and len(parts) < 6:
                lo, hi = (int(v, 16) for v in parts[0].split("-"))
                with open(os.path.join(args.out, f"code{k}.bin"), "wb") as f:
                    f.write(ctypes.string_at(lo, hi - lo))
                maps.write(f"{k} {lo:x} {hi:x}\n")
                k += 1


def disassemble(path, base):
    # (--insn-width: each instruction's bytes on its one line; objdump
    # otherwise continues one of over 7 bytes on a line of bytes alone)
    out = subprocess.run(["objdump", "-D", "-b", "binary", "-mi386:x86-64", "--insn-width=16",
                          f"--adjust-vma={base:#x}", path],
                         capture_output=True, text=True, check=True).stdout
    ins = []
    for line in out.splitlines():
        m = re.match(r"\s*([0-9a-f]+):\s+(?:[0-9a-f]{2} )+\s*(.*)", line)
        if m and m.group(2).strip():
            ins.append((int(m.group(1), 16) - base, m.group(2).strip()))
    return ins


def analyse(samples, code, base):
    """The kernel's loops and stretches with their shares of ``samples``
    (a Counter of sampled addresses) over the machine code ``code`` (bytes)
    loaded at ``base``: (inside, loops, stretches, ins). ``inside``: the
    samples in the code; ``loops``: (start, end, share %), a loop from a
    backward jump's target to the jump; ``stretches``: (start, end, share %,
    instructions) between loop boundaries; offsets from ``base``."""
    with tempfile.NamedTemporaryFile(suffix=".bin") as f:
        f.write(code)
        f.flush()
        ins = disassemble(f.name, base)
    end = len(code)
    inside = _samples_in(samples, base, base + end)

    def share(lo, hi):
        return 100 * _samples_in(samples, base + lo, base + hi) / max(inside, 1)
    loops, cuts = [], {0, end}
    for a, text in ins:
        m = re.match(r"j\w+\s+0x([0-9a-f]+)", text)
        t = int(m.group(1), 16) - base if m else -1
        if 0 <= t <= a:                  # a backward jump within the code
            loops.append((t, a, share(t, a + 1)))
            cuts |= {t, a + 1}
    cuts = sorted(cuts)
    stretches = [(lo, hi, share(lo, hi), [t for a, t in ins if lo <= a < hi])
                 for lo, hi in zip(cuts, cuts[1:])]
    return inside, loops, stretches, ins


def _samples_in(samples, lo, hi):
    """The samples at addresses lo <= a < hi."""
    return sum(c for a, c in samples.items() if lo <= a < hi)


def _fp_ops(part, kind):
    """Vector instructions whose mnemonics end in ``kind`` ('pd': float64,
    'ps': float32: vaddpd, vfmadd213ps, vmovupd...); those starting vp
    (integer ones such as vpcmpd, and vpermps) are left out."""
    return sum(re.match(rf"v(?!p)\w*{kind}$", t.split()[0]) is not None for t in part)


def report(samples, work):
    maps = os.path.join(work, "maps.txt")
    regions = [(int(k), int(lo, 16), int(hi, 16))
               for k, lo, hi in (line.split() for line in open(maps))] \
        if os.path.exists(maps) else []
    if not regions:
        sys.exit("kernel_profile: the child wrote no kernel code (did it fail?)")
    k, base, _ = max(regions, key=lambda r: _samples_in(samples, r[1], r[2]))
    with open(os.path.join(work, f"code{k}.bin"), "rb") as f:
        code = f.read()
    inside, loops, stretches, ins = analyse(samples, code, base)
    if inside == 0:
        sys.exit("kernel_profile: no sample fell in the kernel's code")
    total = sum(samples.values())
    print(f"the kernel holds {100 * inside / total:.1f}% of {total} samples")
    print("loops (start-end: share of the kernel's samples):")
    for lo, hi, sh in loops:
        print(f"  {lo:6x}-{hi:6x} {sh:5.1f}%")
    print("stretches between loop boundaries (over 0.5%):")
    for lo, hi, sh, part in stretches:
        if sh > 0.5:
            print(f"  {lo:6x}-{hi:6x} {sh:5.1f}%  {len(part):5d} instructions, "
                  f"pd {_fp_ops(part, 'pd')}, ps {_fp_ops(part, 'ps')}, "
                  f"gathers {sum('gather' in t for t in part)}")
    print("hottest instructions (the sample's instruction; the one before it):")
    where = {a: i for i, (a, _) in enumerate(ins)}
    top = sorted(((c, a - base) for a, c in samples.items() if a - base in where), reverse=True)
    for c, a in top[:12]:
        i = where[a]
        before = ins[i - 1][1][:48] if i > 0 else ""
        print(f"  {100 * c / inside:5.1f}%  {a:6x}  {ins[i][1][:48]:48s} | {before}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("surface")
    ap.add_argument("--rays", choices=("camera", "incoherent", "shadow"), default="camera",
                    help="shadow: the bench's any-hit rays from the camera rays' hits")
    ap.add_argument("--res", type=int, default=512, help="camera rays per side (incoherent: "
                    "res^2 rays; shadow: from the hits of res^2 camera rays)")
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--child-out", dest="out", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.out:
        return child(args)
    for tool in ("perf", "objdump"):
        if shutil.which(tool) is None:
            sys.exit(f"kernel_profile: needs {tool!r} on the PATH")
    with tempfile.TemporaryDirectory() as work:
        data = os.path.join(work, "perf.data")
        cmd = [sys.executable, "-m", "lgshape.bench.kernel_profile", args.surface,
               "--rays", args.rays, "--res", str(args.res), "--seconds", str(args.seconds),
               "--child-out", work]
        rec = subprocess.run(["perf", "record", "-o", data, "--"] + cmd,
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        if rec.returncode != 0:
            sys.exit(f"kernel_profile: perf record or the profiled child failed "
                     f"({rec.returncode}); the output:\n"
                     f"{rec.stderr[-2000:]}\n(perf may need "
                     "/proc/sys/kernel/perf_event_paranoid <= 2, or a container that allows it)")
        ips = subprocess.run(["perf", "script", "-i", data, "-F", "ip"], capture_output=True,
                             text=True, check=True).stdout.split()
        report(collections.Counter(int(v, 16) for v in ips), work)


if __name__ == "__main__":
    main()
