"""One capture rendered here and on a local Dask cluster of 1 and 2 workers: run time and speed-up,
measured in one run (these machines are shared: compare the ratios, not seconds across runs).

    python scripts/cluster_speedup.py [CONFIG] [--size 640x512] [--spp 16] [--workers 1 2]

Each run has the render cache off and renders the same strata (the same seed); the captures must be
identical, and the script says so. Here, Dr.Jit renders each stratum with all of this machine's
cores; a worker renders with cores / workers-on-its-host threads, several strata at once.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from mbcapture import load_config
from mbcapture.exposure.cluster import start_client
from mbcapture.capture.pipeline import capture_in_memory
from mbcapture.progress import StageStatus


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("config", nargs="?", default="metronome_hdr")
    ap.add_argument("--size", default="640x512")
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    args = ap.parse_args()
    w, h = args.size.split("x")
    cfg = load_config(
        args.config, [f"render.width={w}", f"render.height={h}", f"render.spp={args.spp}", "render.cache=off"]
    )
    capture_in_memory(cfg, StageStatus(False))  # compiles this process's kernels
    t = time.perf_counter()
    here = capture_in_memory(cfg, StageStatus(False))
    base = time.perf_counter() - t
    print(f"{args.config} at {args.size}, {here.plan.passes} passes x {args.spp} spp")
    print(f"  here              {base:7.2f} s   x1.00")
    for n in args.workers:
        client = start_client(n)
        try:
            capture_in_memory(cfg, StageStatus(False), client=client)  # the workers compile theirs
            t = time.perf_counter()
            res = capture_in_memory(cfg, StageStatus(False), client=client)
            s = time.perf_counter() - t
        finally:
            cluster = client.cluster
            client.close()
            cluster.close()
        same = np.array_equal(res.reads_dn, here.reads_dn)
        print(
            f"  {n} worker(s)       {s:7.2f} s   x{base / s:.2f} speed-up  (renders on the cluster "
            f"{res.report['cluster']['seconds']:.2f} s; identical to here: {same})"
        )


if __name__ == "__main__":
    main()
