"""What the time-of-flight phasor channels cost: one render of the tof_room scene's groups alone against the
same render with the illuminator's phasor channels at one and at two frequencies (sine: one harmonic each;
square to the 5th: three), at equal samples, alternated in one run (the machine is shared: ratios, not times).

    python scripts/benchmark_tof.py [--width 320 --height 240 --spp 16 --repeats 3]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from mbcapture.render import Renderer
from mbcapture.scene.scenes import load_module, make_scene
from mbcapture.sensor.demodulation import basis_name, wavenumber


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    scene = make_scene("tof_room", load_module("tof_room").Params())
    r = Renderer(scene, args.width, args.height, max_depth=4)

    def channels(freqs, harmonics):
        ks = [wavenumber(h * f) for f in freqs for h in harmonics]
        return ["ambient", "illuminator"] + [basis_name("illuminator", k, p) for k in ks for p in ("cos", "sin")]

    cases = {
        "groups alone (intensity)": ["ambient", "illuminator"],
        "1 frequency, sine": channels([20e6], [1]),
        "2 frequencies, sine": channels([20e6, 100e6], [1]),
        "1 frequency, square to h=5": channels([20e6], [1, 3, 5]),
    }
    for names in cases.values():  # compile every kernel first
        r.raw_render(0.0, 1, 0, names)
    times = {c: [] for c in cases}
    for rep in range(args.repeats):
        for case, names in cases.items():
            t0 = time.perf_counter()
            r.raw_render(0.0, args.spp, 100 + rep, names)
            times[case].append(time.perf_counter() - t0)
    base = np.median(times["groups alone (intensity)"])
    print(f"tof_room {args.width}x{args.height}, {args.spp} spp, max_depth 4, median of {args.repeats}:")
    for case, t in times.items():
        print(f"  {case:30s} {np.median(t):7.2f} s   {np.median(t) / base:5.2f}x")


if __name__ == "__main__":
    main()
