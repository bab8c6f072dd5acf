"""On a Bayer sensor, should the HDR merge run before or after demosaicing, and should the merged radiance be
demosaiced as it is or in a logarithmic domain? Prints the metronome's HDR error each way for each
demosaicing method, from the same capture (apps/hdr.py merges first and demosaics in the logarithmic domain,
:func:`mbcapture.sensor.cfa.demosaic_hdr`), and the error of demosaicing the noise-free truth alone both ways.

    python scripts/cfa_hdr_order.py [--size 320x256] [--spp 16]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from mbcapture import load_config
from mbcapture.apps import hdr as hdr_app
from mbcapture.apps.hdr import REL_MSE_EPS_RADIANCE, demosaic_floor, luminance_cd_m2
from mbcapture.metrics import pu21_psnr, relative_mse
from mbcapture.capture.pipeline import capture_in_memory
from mbcapture.progress import StageStatus
from mbcapture.reconstruct.hdr import merge_hdr
from mbcapture.sensor.cfa import DEMOSAIC_METHODS, demosaic, demosaic_hdr, to_mosaic

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="320x256")
    ap.add_argument("--spp", type=int, default=16)
    args = ap.parse_args()
    w, h = args.size.split("x")
    print(f"{'demosaic':<12} {'order':<34} {'relMSE':>8} {'PU21-PSNR dB':>13}")
    for method in DEMOSAIC_METHODS:
        cfg = load_config(
            ROOT / "configs" / "metronome_hdr.yaml",
            [
                f"render.width={w}",
                f"render.height={h}",
                f"render.spp={args.spp}",
                "sensor.cfa=RGGB",
                f"sensor.demosaic={method}",
            ],
        )
        res = capture_in_memory(cfg, StageStatus(False))
        truth = res.images["truth"]
        k_e = np.array(list(res.report["electrons_per_render_unit_second"].values()))
        exposure_s = np.array([r["exposure_s"] for r in res.report["reads"]])
        # the sensor stage's demosaiced reads, merged as a three-channel sensor's would be
        first = (
            merge_hdr(
                res.reads_dn,
                exposure_s,
                cfg.sensor,
                method=res.report["metrics"]["hdr_method"],
                cumulative=True,
                saturated=res.saturated,
            ).rate_e_per_s
            / k_e
        )
        # the same capture (the same seeds) with the merged radiance demosaiced as it is
        hdr_app.demosaic_hdr = lambda mosaic, pattern, name, floor: demosaic(mosaic, pattern, name)
        try:
            linear = capture_in_memory(cfg, StageStatus(False)).images["radiance"]
        finally:
            hdr_app.demosaic_hdr = demosaic_hdr
        floor = demosaic_floor(cfg.sensor, k_e, exposure_s)
        mosaic = to_mosaic(truth, cfg.sensor.cfa)
        rows = (
            ("merge first, log domain (the app)", res.images["radiance"]),
            ("merge first, linear", linear),
            ("demosaic first", first),
            ("truth alone, log domain", demosaic_hdr(mosaic, cfg.sensor.cfa, method, floor)),
            ("truth alone, linear", demosaic(mosaic, cfg.sensor.cfa, method)),
        )
        for order, radiance in rows:
            print(
                f"{method:<12} {order:<34} {relative_mse(radiance, truth, eps=REL_MSE_EPS_RADIANCE):8.4f} "
                f"{pu21_psnr(luminance_cd_m2(radiance), luminance_cd_m2(truth)):13.2f}"
            )


if __name__ == "__main__":
    main()
