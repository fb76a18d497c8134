"""The final pose graph of `slam.refine` applied to finished runs: ATE and drift before and after, per run.

It is the step a run with `slam.refine.enabled=true` takes after its last frame (the same functions, the run's own
config and seed), applied to the trajectory a run wrote, so one tracked run measures both; never asserted in tests.

    python benchmarks/refine_graph.py runs/s7 runs/handheld            # slam.refine's defaults (links 8 and 16 apart)
    python benchmarks/refine_graph.py runs/s7 --set "slam.refine.gaps=[4,8,16]"

Prints per run: ATE [cm] and drift [cm per 100 frames] (`inrslam.eval.trajectory`) of the written trajectory and of
the refined one, the links used and left out, and the time of the links and of the graph.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path, help="finished run directories (trajectory.txt, trajectory_gt.txt)")
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="overrides of the run's config")
    args = ap.parse_args()
    import numpy as np

    from inrslam.config import load_config
    from inrslam.datasets import open_dataset
    from inrslam.eval.trajectory import ate, drift_per_100
    from inrslam.io.trajectory import read_tum
    from inrslam.slam.trajectory_graph import frame_pyramid, photometric_links, refine_trajectory

    print(f"{'run':<28} {'ATE before':>10} {'after':>7} {'drift before':>12} {'after':>7} {'links':>6} {'left out':>8}"
          f" {'links [s]':>9} {'graph [s]':>9}")
    for run in args.runs:
        cfg = load_config(run / "config.yaml", preset=None, overrides=["slam.refine.enabled=true", *args.set],
                          check_variants=False)
        dataset = open_dataset(cfg.data)
        _, est = read_tum(run / "trajectory.txt")
        _, gt = read_tum(run / "trajectory_gt.txt")
        rc = cfg.slam.refine
        t0 = time.perf_counter()
        links, dropped = photometric_links(lambda k: frame_pyramid(dataset[k], cfg.slam), est, rc.gaps,
                                           cfg.slam.photo, rc.max_shift, cfg.seed)
        t1 = time.perf_counter()
        new = refine_trajectory(est, links, rc)
        t2 = time.perf_counter()

        def score(T: np.ndarray) -> tuple[float, float]:
            return 100 * ate(T, gt)["rmse"], 100 * drift_per_100(T, gt)["drift_m_per_100"]

        (a0, d0), (a1, d1) = score(est), score(new)
        print(f"{run.name:<28} {a0:>10.3f} {a1:>7.3f} {d0:>12.3f} {d1:>7.3f} {len(links):>6} {dropped:>8}"
              f" {t1 - t0:>9.1f} {t2 - t1:>9.1f}")


if __name__ == "__main__":
    main()
