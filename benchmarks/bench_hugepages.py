"""The map's large tables in 2 MB pages (transparent huge pages) against ordinary 4 KB pages, interleaved in one
process on the same map and rays (median of --reps): a tracking and a mapping iteration at `paper` settings with
every fused kernel. Never asserted in tests; Linux only.

    python benchmarks/bench_hugepages.py                  # dense, builtin:room
    python benchmarks/bench_hugepages.py --encoding hash

The lookups gather 8 corners per point and level from tables of up to 45 MB, scattered over about 11,000 4 KB
pages: if address translation (TLB misses) were part of their cost, tables in 2 MB pages would shorten them. Each
parameter above 4 MB is copied into an anonymous mapping advised `MADV_HUGEPAGE` (aligned to 2 MB) and swapped in
as the parameter's storage; the values are the same, so are the results. Prints the system's AnonHugePages (all
processes) after the copy: if it is below the tables' size, the kernel gave them few or no huge pages
(`/sys/kernel/mm/transparent_hugepage/enabled` set to `never`, or memory too fragmented).
See docs/speed.md, "The lookups' backward".
"""

from __future__ import annotations

import argparse
import mmap

from iteration_setup import FUSED, add_map_arguments, interleaved, machine_line, paper_map

HUGE = 2 << 20  # bytes in a huge page (x86-64)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_map_arguments(ap, encodings=["dense", "hash"])
    args = ap.parse_args()
    import numpy as np
    import torch

    bench = paper_map(args.encoding, args.data, args.frames, FUSED)
    big = [p for p in bench.model.parameters() if p.numel() * p.element_size() > 4 << 20]
    maps = []  # the mappings must outlive the tensors viewing them

    def in_huge_pages(t: torch.Tensor) -> torch.Tensor:
        nbytes = t.numel() * t.element_size()
        mm = mmap.mmap(-1, nbytes + HUGE)
        mm.madvise(mmap.MADV_HUGEPAGE)  # before the first touch: the copy below faults in 2 MB pages
        raw = np.frombuffer(mm, dtype=np.uint8)
        start = (-raw.ctypes.data) % HUGE
        out = torch.from_numpy(raw[start:start + nbytes]).view(t.dtype).view(t.shape)
        out.copy_(t)
        maps.append(mm)
        return out

    small = [p.data for p in big]
    huge = [in_huge_pages(p.data) for p in big]
    with open("/proc/meminfo") as f:
        anon = next(line.split(":")[1].strip() for line in f if line.startswith("AnonHugePages"))
    print(machine_line(f"{args.data}, F={args.encoding}, paper + every fused kernel; tables "
                       f"{[tuple(p.shape) for p in big]}, AnonHugePages {anon}; median ms of {args.reps}"))

    def use(tables):
        def setter() -> None:
            for p, t in zip(big, tables):
                p.data = t
        return setter

    for name, step in [("tracking iteration", bench.track_iter), ("mapping iteration", bench.map_iter)]:
        ms = interleaved(step, {"4 KB pages": use(small), "2 MB pages": use(huge)}, args.reps)
        print(f"{name:20s} 4 KB {ms['4 KB pages']:7.2f}   2 MB {ms['2 MB pages']:7.2f}   "
              f"ratio {ms['4 KB pages'] / ms['2 MB pages']:.3f}")


if __name__ == "__main__":
    main()
