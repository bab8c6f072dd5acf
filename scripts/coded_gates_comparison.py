"""What per-pixel gates buy: one-shot multi-flash on the same moving scene, three ways.

    python scripts/coded_gates_comparison.py [--size 640x512] [--cost-spp 16] [--cost-repeats 3] [--write-readme]

(a) a 5-bucket global-gate sensor (configs/multi_flash.yaml: one bucket per LED, one for ambient),
(b) a 2-bucket coded (C2B) sensor with per-pixel codes (configs/coded_multi_flash.yaml: Hadamard;
    also one-hot and random codes, and the Hadamard code with multi_flash.yaml's 10 000 e- buckets),
(c) five sequential frames on a conventional sensor (multi_flash.yaml, capture.sequential: true).

Each capture takes its samples from the noise budget and is scored against the same truths
(app multi_flash: per-light images, depth edges, shadow-free image, photometric-stereo normals).
Prints a markdown table (the README's), then the render cost of the coded capture against the
same capture with global gates: the same strata at ``--cost-spp`` samples, render cache off,
render + accumulate + sensor stage, best of ``--cost-repeats`` alternating runs (one process,
so the ratio is measured on the same machine at the same time).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from mbcapture import load_config
from mbcapture.capture.pipeline import capture_in_memory
from mbcapture.progress import StageStatus

ROOT = Path(__file__).resolve().parents[1]
MF, CODED = ROOT / "configs" / "multi_flash.yaml", ROOT / "configs" / "coded_multi_flash.yaml"

CAPTURES = [
    ("(a) 5 buckets, global gates", MF, []),
    ("(b) 2 buckets, Hadamard code", CODED, []),
    ("(b) 2 buckets, one-hot code", CODED, ["capture.gate_code.family=one_hot"]),
    ("(b) 2 buckets, random code", CODED, ["capture.gate_code.family=random"]),
    (
        "(b) 2 buckets, Hadamard, 10 000 e- buckets",
        CODED,
        ["sensor.full_well_e=10000", "sensor.fd_full_well_e=40000", "sensor.gain_dn_per_e=0.4"],
    ),
    ("(c) 5 sequential frames", MF, ["capture.sequential=true"]),
]


def _fmt(v, spec=".3f") -> str:
    return "n/a" if v is None else format(v, spec)


def row(name: str, res) -> str:
    m = res.report["metrics"]
    de, sf, pl, nm = m["depth_edges"], m["shadow_free"], m["per_light"], m["normals"]
    mov = de.get("moving_region", {})
    spp = res.plan.spp
    return (
        f"| {name} | {_fmt(pl['mean_nrmse'], '.4f')} / {_fmt(pl.get('mean_nrmse_moving'), '.4f')} "
        f"| {_fmt(de['all']['f1'])} / {_fmt(mov.get('f1'))} | {sf['rel_mse']:.4f} "
        f"| {100 * sf.get('residual_shadow_fraction', 0.0):.2f} % "
        f"| {_fmt(nm.get('median_deg'), '.2f')} / {_fmt(nm.get('median_deg_moving'), '.2f')} "
        f"| {m['saturated_px']} | {res.plan.passes} x {int(spp.max())} = {int(spp.sum())} |"
    )


def render_cost(size: list[str], spp: int, repeats: int) -> str:
    """Render + accumulate + sensor of the coded capture against the same strata with global gates."""
    common = size + [f"render.spp={spp}", "render.cache=off", "app.truth_spp=1"]
    runs = {
        "global gates (5 buckets)": load_config(MF, common),
        "per-pixel code (2 buckets, Hadamard)": load_config(CODED, common),
    }
    best: dict[str, float] = {}
    for _ in range(repeats):
        for name, cfg in runs.items():
            res = capture_in_memory(cfg, StageStatus(False))
            t = res.report["timings_s"]
            cost = t.get("render", 0.0) + t.get("accumulate", 0.0) + t.get("sensor", 0.0)
            best[name] = min(best.get(name, float("inf")), cost)
    g, c = best.values()
    line = (
        f"Render + accumulate + sensor stage at {spp} spp (render cache off, best of {repeats} alternating runs): "
        f"global gates {g:.2f} s, per-pixel code {c:.2f} s, ratio {c / g:.3f}."
    )
    print("\n" + line)
    return line


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", default="640x512")
    ap.add_argument("--cost-spp", type=int, default=16)
    ap.add_argument("--cost-repeats", type=int, default=3)
    ap.add_argument("--skip-cost", action="store_true")
    ap.add_argument("--write-readme", action="store_true", help="put the table between README.md's coded_gates markers")
    args = ap.parse_args()
    w, h = args.size.split("x")
    size = [f"render.width={w}", f"render.height={h}"]
    lines = [
        f"Multi-flash scene at {w}x{h}, sliding box; each capture's samples from its noise budget "
        f"(`python scripts/coded_gates_comparison.py --size {args.size}`).",
        "",
        "| capture | per-light NRMSE (all / moving) | depth-edge F1 (all / moving) | shadow-free relMSE "
        "| residual shadow | normals median error, deg (all / moving) | px without a value (saturated; coded: or undetermined) | samples per pixel |",
        "|---|---|---|---|---|---|---|---|",
    ]
    print("\n".join(lines), flush=True)
    for name, path, sets in CAPTURES:
        lines.append(row(name, capture_in_memory(load_config(path, size + sets), StageStatus(False))))
        print(lines[-1], flush=True)
    if not args.skip_cost:
        lines += ["", render_cost(size, args.cost_spp, args.cost_repeats)]
    if args.write_readme:
        write_readme("\n".join(lines))


def write_readme(text: str) -> None:
    """Put ``text`` between README.md's coded_gates markers (nothing else changes)."""
    readme = ROOT / "README.md"
    begin, end = "<!-- BEGIN coded_gates -->", "<!-- END coded_gates -->"
    old = readme.read_text()
    if begin not in old or end not in old:
        raise SystemExit(f"README.md has no {begin} ... {end} markers")
    head, rest = old.split(begin, 1)
    readme.write_text(head + begin + "\n" + text + "\n" + end + rest.split(end, 1)[1])
    print("wrote README.md")


if __name__ == "__main__":
    main()
