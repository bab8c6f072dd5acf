"""Search chop codes for the two-bucket flutter shutter; print how they compare with Raskar et al.'s.

    python scripts/flutter_code_search.py [--chops 52] [--trials 5000] [--seed 0]

Raskar, Agrawal and Tumblin (2006) chose their 52-chop code by a randomized search for a flat,
zero-free spectrum of the one (open) exposure. With two buckets the reconstruction sees the open
chops and their complement together, so the figure of merit here is the noise of the joint least
squares deblur (app.deblur fourier): sqrt(mean_w 1 / (|H_1(w)|^2 + |H_2(w)|^2)) for unit white noise per
read (mbcapture.apps.flutter_shutter.white_noise_gain), a blur of one pixel per chop, a row three codes
long. Random codes with half the chops open (the first and last open, so the blur's length is the
code's) are drawn; the best is printed with its joint and single-code (open bucket alone) noise, as
ratios to Raskar's code and to the box.
Use a found code with ``--set app.code=<bits>``.
"""

from __future__ import annotations

import argparse

import numpy as np

from mbcapture.apps.flutter_shutter import RASKAR_2006
from mbcapture.reconstruct.deblur import white_noise_gain


def noise(code: np.ndarray, joint: bool, n: int) -> float:
    shifts = np.arange(len(code)) - len(code) // 2
    samples = [(shifts, code.astype(float))] + ([(shifts, 1.0 - code)] if joint else [])
    return white_noise_gain(samples, np.ones(len(samples)), n, 1.0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--chops", type=int, default=52)
    ap.add_argument("--trials", type=int, default=5000)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    n_px = 3 * args.chops
    rng = np.random.default_rng(args.seed)
    raskar = np.array([int(c) for c in RASKAR_2006]) if args.chops == 52 else None
    box = noise(np.ones(args.chops, int), False, n_px)
    best = None
    for _ in range(args.trials):
        code = np.zeros(args.chops, int)
        code[0] = code[-1] = 1  # the exposure starts and ends open: the kernel's length is the blur's
        code[1 + rng.choice(args.chops - 2, args.chops // 2 - 2, replace=False)] = 1
        j = noise(code, True, n_px)
        if best is None or j < best[0]:
            best = (j, code)
    j, code = best
    print(
        f"box (one bucket, all chops):       noise {box:.4g}"
        + ("  (its spectrum has zeros: singular)" if box > 1e6 else "")
    )
    if raskar is not None:
        rj, rs = noise(raskar, True, n_px), noise(raskar, False, n_px)
        print(f"Raskar 2006, open bucket only:     noise {rs:.4f}")
        print(f"Raskar 2006, both buckets (joint): noise {rj:.4f}")
    s = noise(code, False, n_px)
    print(f"best of {args.trials} random codes ({code.sum()} of {args.chops} open): {''.join(map(str, code))}")
    print(
        f"  open bucket only: noise {s:.4f}; both buckets (joint): noise {j:.4f}"
        + (f"  ({rj / j:.3f}x less than Raskar's joint)" if raskar is not None else "")
    )


if __name__ == "__main__":
    main()
