"""Run -> inspect -> compare, through the Python API (the tests run this file).

    python examples/run_inspect_compare.py                 # two encodings on builtin:room, quick preset
    python examples/run_inspect_compare.py --out runs/example --frames 20 --encodings dense hash triplane

Each run is a normal run directory (`inrslam view`-, `inrslam eval`- and evo-readable); `inrslam.load_run` reads
one back without touching it.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np

import inrslam


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=None, help="folder for the runs (default: a temporary folder)")
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--encodings", nargs="+", default=["dense", "hash"])
    ap.add_argument("--preset", default="quick")
    args = ap.parse_args()
    out = Path(args.out or tempfile.mkdtemp(prefix="inrslam-example-"))

    # 1. run: one SLAM run per scene representation F, same everything else
    runs = {}
    for enc in args.encodings:
        runs[enc] = inrslam.run(out / enc, preset=args.preset, overwrite=True,
                                overrides=[f"data.max_frames={args.frames}", f"field.encoding={enc}"])

    # 2. inspect one: trajectory against ground truth, keyframes, the mesh, a render of the map
    r = runs[args.encodings[0]]
    err = np.linalg.norm(r.est[:, :3, 3] - r.gt[:, :3, 3], axis=1)
    print(f"{r.root}: {len(r.est)} poses, keyframes {r.keyframes}, last-frame error {err[-1] * 100:.2f} cm")
    mesh = r.mesh()
    print(f"mesh: {len(mesh.vertices) if mesh is not None else 0} vertices")
    rgb, depth = r.render(r.est[-1])
    print(f"render of the last frame: {rgb.shape[1]}x{rgb.shape[0]} px, median depth {np.median(depth):.2f} m")

    # 3. compare: the metrics every run wrote
    print(f"{'F':10s} {'ATE [cm]':>9s} {'Acc [cm]':>9s} {'PSNR [dB]':>10s} {'track [ms]':>11s}")
    for enc, run in runs.items():
        m = run.metrics
        acc = f"{m['acc_m'] * 100:9.2f}" if m.get("acc_m") is not None else f"{'-':>9s}"
        print(f"{enc:10s} {m['ate_rmse_m'] * 100:9.2f} {acc} {m['psnr_db']:10.2f} {m['track_ms_per_frame']:11.0f}")


if __name__ == "__main__":
    main()
