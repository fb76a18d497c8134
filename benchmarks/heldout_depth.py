"""Held-out depth L1 of finished runs with both depth estimators (`eval.heldout_depth`: expected = G's weighted mean,
surface = the SDF's first zero crossing, searched again where the samples may have stepped over a thin object when
`eval.heldout_refine` or `--refine` > 0), against the observed depth and, on the built-in scenes, the noise-free
depth. Re-renders the run's held-out frames (same frames, poses and samples as its evaluation) from its final
checkpoint (`output.keep_checkpoint`, on by default); the run folder is only read. Never asserted in tests.

    python benchmarks/heldout_depth.py runs/acc_room runs/acc_handheld
    python benchmarks/heldout_depth.py runs/acc_room --refine 0      # the uniform surface search only
"""

from __future__ import annotations

import argparse


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--refine", type=int, default=None,
                    help="samples per refined interval of the surface search (default: the run's eval.heldout_refine)")
    args = ap.parse_args()

    import torch

    import inrslam
    from inrslam.datasets import open_dataset
    from inrslam.eval.heldout import heldout_metrics

    print("| run | depth L1 [cm]: expected vs observed | surface vs observed | expected vs true | surface vs true | "
          "PSNR [dB] | frames |")
    print("|:--|--:|--:|--:|--:|--:|--:|")
    for path in args.runs:
        run = inrslam.load_run(path)
        cfg = run.config
        ds = open_dataset(cfg.data)
        cells = {}
        for mode in ("expected", "surface"):
            refine = cfg.eval.heldout_refine if args.refine is None else args.refine

            def render(c2w, intr, mode=mode, model=run.model, n=cfg.eval.heldout_samples, refine=refine):
                with torch.no_grad():
                    return model.render_image(torch.as_tensor(c2w, dtype=torch.float32), intr, n_coarse=n, depth=mode,
                                              refine=refine)
            m = heldout_metrics(render, ds, run.est, cfg.eval.heldout_every, cfg.eval.heldout_max,
                                offset=cfg.slam.map_every // 2)
            cells[mode] = (m["depth_l1_m"], m.get("depth_l1_true_m"))
            psnr = m["psnr_db"]  # the colour does not depend on the depth estimator

        def fmt(v):
            return "–" if v is None else f"{100 * v:.2f}"

        print(f"| {path} | {fmt(cells['expected'][0])} | {fmt(cells['surface'][0])} | {fmt(cells['expected'][1])} | "
              f"{fmt(cells['surface'][1])} | {psnr:.2f} | {len(m['heldout_frames'])} |", flush=True)


if __name__ == "__main__":
    main()
