"""Markdown table of finished run directories: ATE, drift, held-out depth L1 (against the observed depth and, on the
built-in scenes, their noise-free depth) / PSNR, time per frame, fallbacks.

    python benchmarks/preset_table.py runs/presets/*          # one row per run directory, in the order given

Reads only what the runs wrote. Runs made with `eval.enabled=false` have no metrics from evaluation: their ATE and
drift are computed here from `trajectory.txt` / `trajectory_gt.txt` with the same functions `inrslam eval` uses.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def row(run_dir: Path) -> dict:
    from inrslam.eval.run import eval_trajectory_files

    m = json.loads((run_dir / "metrics.json").read_text())
    if m.get("drift_m_per_100") is None and (run_dir / "trajectory_gt.txt").is_file():  # older runs: no drift key
        m.update({k: v for k, v in eval_trajectory_files(run_dir / "trajectory.txt",
                                                        run_dir / "trajectory_gt.txt").items() if k not in m or
                  m[k] is None})
    frames = max(int(m.get("frames") or 1) - 1, 1)
    n_map = len([1 for line in (run_dir / "log.jsonl").read_text().splitlines() if '"type": "map"' in line])
    per_frame = ((m.get("track_ms_per_frame") or 0.0) * frames + (m.get("map_ms_per_call") or 0.0) * n_map) / frames
    return {"run": run_dir.name, "ate_cm": _cm(m.get("ate_rmse_m")), "drift_cm": _cm(m.get("drift_m_per_100")),
            "final_cm": _cm(m.get("unaligned_final_m")), "depth_l1_cm": _cm(m.get("depth_l1_m")),
            "depth_l1_true_cm": _cm(m.get("depth_l1_true_m")),
            "psnr": m.get("psnr_db"), "s_per_frame": per_frame / 1e3, "fallbacks": m.get("fallbacks")}


def _cm(v):
    return None if v is None else 100.0 * float(v)


def fmt(v, nd=2) -> str:
    return "—" if v is None else f"{v:.{nd}f}" if isinstance(v, float) else str(v)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path)
    args = ap.parse_args()
    print("| run | ATE [cm] | drift [cm/100 fr] | last-frame error [cm] | depth L1 [cm] | vs true depth [cm] | "
          "PSNR [dB] | s/frame | fallbacks |")
    print("|:--|--:|--:|--:|--:|--:|--:|--:|--:|")
    for d in args.runs:
        if not (d / "metrics.json").is_file():
            continue
        r = row(d)
        print(f"| {r['run']} | {fmt(r['ate_cm'], 3)} | {fmt(r['drift_cm'], 3)} | {fmt(r['final_cm'], 3)} | "
              f"{fmt(r['depth_l1_cm'])} | {fmt(r['depth_l1_true_cm'])} | {fmt(r['psnr'], 1)} | "
              f"{fmt(r['s_per_frame'])} | {fmt(r['fallbacks'])} |")


if __name__ == "__main__":
    main()
