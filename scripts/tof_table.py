"""The time-of-flight designs compared (``mbcapture sweep tof_designs``): the README's table and its figure.

    mbcapture sweep tof_designs --out out/tof_designs
    python scripts/tof_table.py out/tof_designs [--figure docs/images/tof_designs.png]

Reads the sweep's results.parquet; prints a Markdown table (one row per design, frequency set and ambient
level) and draws the moving region's depth error, the flying pixels and the pixels whose taps saw different
surfaces, per design.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import pandas as pd

from mbcapture.output.plots import grouped_bars_png

DESIGNS = ["tof_4tap", "tof_2tap", "tof_2tap_sequential", "tof_1tap"]
LABELS = {
    "tof_4tap": "4 taps, one exposure",
    "tof_2tap": "2 taps, pairs interleaved",
    "tof_2tap_sequential": "2 taps, sequential",
    "tof_1tap": "1 tap, sequential",
}


def _freqs(v) -> str:
    return " + ".join(f"{float(f):g}" for f in (json.loads(v) if isinstance(v, str) else list(v)))


def table(df: pd.DataFrame) -> str:
    cols = [
        "design",
        "MHz",
        "ambient",
        "span, ms",
        "depth noise, mm",
        "MAE all, mm",
        "MAE moving, mm",
        "within 10 mm, moving",
        "flying px",
        "taps saw different surfaces, px",
        "MAE there, mm",
        "render / shot noise",
    ]
    lines = ["| " + " | ".join(cols) + " |", "|" + " --- |" * len(cols)]
    df = df.assign(_order=df["capture.protocol"].map(DESIGNS.index))
    df = df.sort_values(["scene.ambient_scale", "capture.tof.frequencies_mhz", "_order"], key=lambda s: s.astype(str))

    def f(v, fmt="{:.3g}"):
        return "n/a" if v is None or pd.isna(v) else fmt.format(v)

    for _, r in df.iterrows():
        lines.append(
            "| "
            + " | ".join(
                [
                    LABELS[r["capture.protocol"]],
                    _freqs(r["capture.tof.frequencies_mhz"]),
                    f"{r['scene.ambient_scale']:g}x",
                    f(r["capture_span_s"] * 1e3, "{:.3g}"),
                    f(r["metrics.median_depth_sigma_mm"]),
                    f(r["metrics.depth.all.mae_mm"]),
                    f(r["metrics.depth.moving_region.mae_mm"]),
                    f(r["metrics.depth.moving_region.within_tolerance"], "{:.1%}"),
                    f(r["metrics.flying_pixels.measured"], "{:.0f}"),
                    f(r["metrics.motion_artefact.px"], "{:.0f}"),
                    f(r["metrics.motion_artefact.error_there.mae_mm"]),
                    f(r["render_error.to_shot_noise_variance_median"], "{:.2g}"),
                ]
            )
            + " |"
        )
    return "\n".join(lines)


def figure(df: pd.DataFrame) -> bytes:
    keys = sorted({(_freqs(v), a) for v, a in zip(df["capture.tof.frequencies_mhz"], df["scene.ambient_scale"])})
    categories = [LABELS[d] for d in DESIGNS]

    def series(metric):
        out = {}
        for freqs, amb in keys:
            rows = df[(df["capture.tof.frequencies_mhz"].map(_freqs) == freqs) & (df["scene.ambient_scale"] == amb)]
            by = dict(zip(rows["capture.protocol"], rows[metric]))
            out[f"{freqs} MHz, ambient {amb:g}x"] = [float(by.get(d, float("nan"))) for d in DESIGNS]
        return out

    return grouped_bars_png(
        categories,
        [
            ("depth MAE in the moving region, mm", series("metrics.depth.moving_region.mae_mm")),
            ("flying pixels at depth edges", series("metrics.flying_pixels.measured")),
            ("pixels whose taps saw different surfaces", series("metrics.motion_artefact.px")),
        ],
        title="tof_room at 640 x 480: a box sliding at 1.5 m/s, 1 ms of illuminator per frequency (mbcapture sweep tof_designs)",
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sweep_dir", type=Path)
    ap.add_argument("--figure", type=Path, default=None)
    args = ap.parse_args()
    df = pd.read_parquet(args.sweep_dir / "results.parquet")
    df = df[df["status"] == "ok"]
    print(table(df))
    if args.figure is not None:
        tmp = args.figure.with_name(f".{args.figure.name}.tmp")
        tmp.write_bytes(figure(df))
        os.replace(tmp, args.figure)


if __name__ == "__main__":
    main()
