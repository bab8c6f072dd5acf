"""HDR signal-to-noise ratio against scene radiance for three capture protocols.

The protocols, the sensor model they run through and the SNR estimate are in
:mod:`mbcapture.studies.snr` (also used by ``mbcapture figures``); the default sensor here has
fixed-pattern noise off unless ``--fixed-pattern``.

For a static scene interleaved and sequential differ only by dark current; sequential's
drawback is motion, which this script does not model. At equal T, photon_efficient collects
the photons of 8T against 15T for the others, so in the shot-noise-limited middle of the
range it trails them by about sqrt(8/15) = 0.73; it wins where the others' 8T exposure
saturates (its 8T is spread over four buckets) and in the read-noise-limited dark end. Its
gain is capture time and motion blur (section 4), not SNR per unit T. SNR = mean / std of the merged rate
over many pixels with identical expected electrons (green channel), computed where at least
half of the pixels are valid (not saturated in every read).

The script feeds expected electrons K * L * exposure directly (no rendering).

Usage: python scripts/snr_curves.py --out out/snr [--unit-exposure-s 1e-3]
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mbcapture.sensor import SensorConfig, electrons_per_radiance_second  # noqa: E402
from mbcapture.studies.snr import GREEN, REPORT_RADIANCES, radiance_range, snr_curves  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="output directory (PNG and CSV)")
    parser.add_argument("--unit-exposure-s", type=float, default=1e-3, help="T, the shortest exposure, seconds")
    parser.add_argument("--pixels", type=int, default=20_000, help="pixel samples per radiance level")
    parser.add_argument("--levels", type=int, default=61, help="radiance levels on the log axis")
    parser.add_argument("--seed", type=int, default=0, help="seed of the shot and read noise")
    parser.add_argument("--fixed-pattern", action="store_true", help="keep the default PRNU/DSNU (off by default)")
    args = parser.parse_args(argv)
    if args.unit_exposure_s <= 0 or args.pixels < 2 or args.levels < 2:
        parser.error("--unit-exposure-s must be > 0, --pixels and --levels >= 2")

    cfg = SensorConfig() if args.fixed_pattern else SensorConfig(prnu=0.0, dsnu_e=0.0)
    k_green = electrons_per_radiance_second(cfg)[GREEN]
    radiance = radiance_range(cfg, args.unit_exposure_s, args.levels)
    curves = snr_curves(cfg, radiance, args.unit_exposure_s, args.pixels, args.seed)

    args.out.mkdir(parents=True, exist_ok=True)
    csv_path = args.out / "snr_curves.csv"
    with csv_path.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["radiance_w_m2_sr", "electrons_per_unit_exposure", *(f"snr_{n}" for n in curves)])
        for i, L in enumerate(radiance):
            writer.writerow(
                [f"{L:.6g}", f"{k_green * L * args.unit_exposure_s:.6g}", *(f"{curves[n][i]:.6g}" for n in curves)]
            )

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    for name, snr in curves.items():
        ax.plot(radiance, snr, label=name, lw=1.6)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("scene radiance L, green channel (W m$^{-2}$ sr$^{-1}$)")
    ax.set_ylabel("HDR SNR, mean / std of merged rate (ratio)")
    ax.set_title(f"HDR SNR, exposures T, 2T, 4T, 8T with T = {args.unit_exposure_s * 1e3:g} ms")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    png_path = args.out / "snr_curves.png"
    fig.savefig(png_path, dpi=150)
    plt.close(fig)

    print(f"wrote {csv_path} and {png_path}")
    print(
        f"{'level':<6}{'L (W m^-2 sr^-1)':>18}{'e-/T':>10}{'SNR PE':>10}"
        f"{'gain vs interleaved':>22}{'gain vs sequential':>20}"
    )
    for level, L in REPORT_RADIANCES.items():
        i = int(np.flatnonzero(radiance == L)[0])
        pe, il, sq = (curves[n][i] for n in ("photon_efficient", "interleaved", "sequential"))
        print(
            f"{level:<6}{L:>18.3g}{k_green * L * args.unit_exposure_s:>10.3g}{pe:>10.2f}"
            f"{pe / il:>22.3f}{pe / sq:>20.3f}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
