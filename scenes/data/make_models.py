"""Writes the primitives files of scenes/particles.xml (run from anywhere:
``python scenes/data/make_models.py``; fixed seeds, so the files are
reproducible).

- ``splash.prims``: 2000 soft blobs of a crown splash (a ring of rising
  droplet jets over a pool), for ``combine="blend"``;
- ``towers.prims``: 1200 boxes, capsules and spheres of a little city
  block, for ``combine="union"``.
"""
import os

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))


def splash(n=2000, seed=7):
    rng = np.random.default_rng(seed)
    rows = []
    # the pool: a flat disc of blobs
    k = n // 3
    r = 1.1 * np.sqrt(rng.uniform(0, 1, k))
    a = rng.uniform(0, 2 * np.pi, k)
    for i in range(k):
        rows.append(("sphere", r[i] * np.cos(a[i]), r[i] * np.sin(a[i]),
                     rng.uniform(-0.05, 0.03), 0.16))
    # the crown: jets rising from a ring, thinning into droplets
    jets = 24
    per = (n - k) // jets
    for j in range(jets):
        phi = 2 * np.pi * j / jets + rng.uniform(-0.05, 0.05)
        h = rng.uniform(0.6, 1.0)
        for s in np.linspace(0, 1, per):
            rad = 0.62 + 0.25 * s
            z = h * np.sin(np.pi * 0.5 * s) * (1.0 - 0.15 * s)
            jitter = rng.normal(0, 0.012, 3)
            size = 0.085 * (1 - 0.55 * s) + (0.03 if s > 0.92 else 0.0)
            rows.append(("sphere", rad * np.cos(phi) + jitter[0], rad * np.sin(phi) + jitter[1],
                         z + jitter[2], size))
    with open(os.path.join(HERE, "splash.prims"), "w") as fh:
        fh.write("# crown splash: %d soft blobs (sphere cx cy cz R), blend\n" % len(rows))
        for kind, *v in rows:
            fh.write(kind + " " + " ".join(f"{x:.5f}" for x in v) + "\n")
    return len(rows)


def towers(seed=3):
    rng = np.random.default_rng(seed)
    rows = []
    g = 14
    for i in range(g):
        for j in range(g):
            x, y = (i - (g - 1) / 2) * 0.16, (j - (g - 1) / 2) * 0.16
            h = 0.05 + 0.5 * rng.uniform() ** 2 * np.exp(-(x * x + y * y) / 0.8)
            rows.append(("box", x, y, h, 0.06, 0.06, h, 0.01))
            # a roof: a sphere or a capsule antenna
            if rng.uniform() < 0.5:
                rows.append(("sphere", x, y, 2 * h, 0.045))
            else:
                rows.append(("capsule", x, y, 2 * h, x, y, 2 * h + 0.12, 0.012))
            # windows: small boxes on the faces
            for _ in range(4):
                side = rng.integers(4)
                zz = rng.uniform(0.02, max(2 * h - 0.03, 0.03))
                dx, dy = [(0.061, 0), (-0.061, 0), (0, 0.061), (0, -0.061)][side]
                rows.append(("box", x + dx, y + dy, zz, 0.008 if dx else 0.02,
                             0.008 if dy else 0.02, 0.012, 0.0))
    with open(os.path.join(HERE, "towers.prims"), "w") as fh:
        fh.write("# a city block: %d boxes, spheres and capsules, union\n" % len(rows))
        for kind, *v in rows:
            fh.write(kind + " " + " ".join(f"{x:.5f}" for x in v) + "\n")
    return len(rows)


if __name__ == "__main__":
    print("splash.prims:", splash(), "primitives")
    print("towers.prims:", towers(), "primitives")
