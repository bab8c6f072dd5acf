"""Where a capture's memory goes: the resident memory at the start and end of each stage and its peak
inside it, from a thread that samples /proc/self/status every 10 ms: all of it (VmRSS) and its anonymous
part (RssAnon), which leaves out the pages of files mapped into memory, such as a spilled film's
(render.spill): those the kernel writes back and drops when memory is short.

    python scripts/memory_stages.py CONFIG [--out DIR] [--set KEY=VALUE ...]
    python scripts/memory_stages.py metronome_hdr --set render.width=1280 --set render.height=1024 \\
        --set render.spp=4 --set render.cache=off --set render.band_rows=64 --set render.tiles=16

Stages: those of report.json's timings_s (render and accumulate once per render band and tile), the
noise report's two estimates (render_error, temporal_error) and the writing of the outputs. A stage
shorter than the sampling period may show a lower peak than it had; the last line is the process's
own high-water mark (VmHWM), which misses nothing, and the highest anonymous memory sampled.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import threading
import time
from contextlib import contextmanager
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import mbcapture.capture.run as capture  # noqa: E402
import mbcapture.capture.pipeline as pipeline  # noqa: E402
from mbcapture import load_config, run_capture  # noqa: E402
from mbcapture.config import resolve_config_path  # noqa: E402
from mbcapture.exposure.resources import anon_bytes, peak_rss_bytes, rss_bytes  # noqa: E402

MIB = 1 << 20


def rss_mib() -> float:
    return rss_bytes() / MIB


class Sampler:
    """The highest resident memory (and anonymous memory) seen since the last :meth:`reset`, and over the run."""

    def __init__(self, period_s: float = 0.01):
        self.peak, self.peak_anon, self.run_anon, self.period_s = 0.0, 0.0, 0.0, period_s
        threading.Thread(target=self._run, daemon=True).start()

    def _run(self) -> None:
        while True:
            anon = anon_bytes() / MIB
            self.peak, self.peak_anon = max(self.peak, rss_mib()), max(self.peak_anon, anon)
            self.run_anon = max(self.run_anon, anon)
            time.sleep(self.period_s)

    def reset(self) -> float:
        self.peak, self.peak_anon = rss_mib(), anon_bytes() / MIB
        return self.peak


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("config")
    ap.add_argument("--out", type=Path, default=None, help="where the outputs go (default: a temporary folder)")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    args = ap.parse_args()
    sampler, rows = Sampler(), []

    def measured(name: str, fn):
        def wrapper(*a, **k):
            start = sampler.reset()
            try:
                return fn(*a, **k)
            finally:
                rows.append((name, start, sampler.peak, rss_mib(), sampler.peak_anon))

        return wrapper

    timer_call = pipeline._Timer.__call__

    @contextmanager
    def timed(self, name):
        start = sampler.reset()
        with timer_call(self, name):
            yield
        rows.append((name, start, sampler.peak, rss_mib(), sampler.peak_anon))

    pipeline._Timer.__call__ = timed
    for name in ("render_error", "temporal_error"):
        setattr(pipeline, name, measured(name, getattr(pipeline, name)))
    capture.write_outputs = measured("write outputs", capture.write_outputs)

    cfg = load_config(resolve_config_path(args.config), args.overrides)
    with tempfile.TemporaryDirectory() as tmp:
        run_capture(cfg, args.out or Path(tmp) / "out", progress=False)
    print(f"{'stage':16s} {'start':>8s} {'peak':>8s} {'end':>8s} {'anon peak':>10s}  MiB")
    for name, start, peak, end, anon in rows:
        print(f"{name:16s} {start:8.0f} {peak:8.0f} {end:8.0f} {anon:10.0f}")
    print(
        f"high-water mark (VmHWM) {peak_rss_bytes() / MIB:.0f} MiB; anonymous memory, highest sampled: "
        f"{sampler.run_anon:.0f} MiB"
    )


if __name__ == "__main__":
    main()
