"""What drawing `mesh.png` costs (`inrslam.eval.mesh_thumbnail`): a finely tessellated plane of about 200,000
triangles (a full-length run's mesh is of that order) drawn several times in one invocation; prints the median
seconds and their ratio to the 2 s budget a run's post-processing allows it. Never asserted in tests.

    python benchmarks/bench_thumbnail.py                   # 201,000 triangles, 5 repeats
    python benchmarks/bench_thumbnail.py --cells 500 --repeats 3
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time

import numpy as np

BUDGET_S = 2.0


def plane(n: int) -> tuple[np.ndarray, np.ndarray]:
    """A 4 x 4 m square of n x n cells (2 n^2 triangles) at z = 0: vertices (V, 3), faces (F, 3)."""
    xs = np.linspace(-2.0, 2.0, n + 1)
    X, Y = np.meshgrid(xs, xs, indexing="ij")
    V = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], 1)
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return V, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cells", type=int, default=317, help="cells per side (2 cells^2 triangles)")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    from inrslam.eval.mesh_thumbnail import mesh_thumbnail

    V, F = plane(args.cells)
    mesh_thumbnail(V, F, up=(0, 0, 1))  # warm-up: imports, first-call allocations
    times = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        mesh_thumbnail(V, F, up=(0, 0, 1))
        times.append(time.perf_counter() - t0)
    med = statistics.median(times)
    print(f"# {platform.machine()}, {len(F):,} triangles, {args.repeats} repeats")
    print(f"median {med:.3f} s (min {min(times):.3f}, max {max(times):.3f}); budget {BUDGET_S:.1f} s: "
          f"ratio {med / BUDGET_S:.2f}")


if __name__ == "__main__":
    main()
