"""``mbcapture figures``: every figure written with its data and the index, deterministically."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from mbcapture import figures
from mbcapture.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
NO_RENDER = [n for n in figures.names() if not figures.spec(n).renders]


def test_schedule_figures_are_written_with_data_and_index(tmp_path):
    entries = figures.make_figures(tmp_path, quick=True, only=NO_RENDER, progress=False)
    assert [e["name"] for e in entries] == NO_RENDER
    for e in entries:
        for f in e["files"]:
            assert (tmp_path / f).stat().st_size > 0, f
        assert (tmp_path / f"{e['name']}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert (tmp_path / f"{e['name']}.pdf").read_bytes()[:5] == b"%PDF-"
    index = (tmp_path / "index.html").read_text()
    assert all(f'src="{n}.png"' in index for n in NO_RENDER)
    assert not any(p.name.startswith(".staging") for p in tmp_path.iterdir())


def test_centroid_figure_checks_the_closed_forms(tmp_path):
    figures.make_figures(tmp_path, quick=True, only=["fig05_centroids"], progress=False)
    data = json.loads((tmp_path / "fig05_centroids.json").read_text())
    assert len(data["rows"]) == 6 and all(row[3] for row in data["rows"])
    seq, mux = data["centroids_sequential_s"], data["centroids_multiplexed_s"]
    assert (seq[1] - seq[0]) / (mux[1] - mux[0]) == pytest.approx(data["N"])


def test_figure_11_simulation_agrees_with_the_analytic_snr(tmp_path):
    figures.make_figures(tmp_path, quick=True, only=["fig11_snr_table"], progress=False)
    rows = json.loads((tmp_path / "fig11_snr_table.json").read_text())["rows"][1:]
    n = json.loads((tmp_path / "fig11_snr_table.json").read_text())["pixels"]
    for _, s, add_a, add_s, pix_a, pix_s in rows:
        # the SNR estimate's relative standard error is ~ sqrt((1 + SNR^2 / 2) / n) / 1 (mean/std ratio)
        tol = 5 * (1 + add_a**2 / 2) ** 0.5 / n**0.5 * add_a
        assert abs(add_s - add_a) < tol and abs(pix_s - pix_a) < 5 * (1 + pix_a**2 / 2) ** 0.5 / n**0.5 * pix_a
    assert all(r[4] > r[2] for r in rows[1:])  # in-pixel addition wins from J2 on


def test_figures_are_deterministic(tmp_path):
    a, b = tmp_path / "a", tmp_path / "b"
    for d in (a, b):
        figures.make_figures(d, quick=True, only=["fig05_centroids", "fig11_snr_table"], progress=False)
    for name in ("fig05_centroids.png", "fig05_centroids.pdf", "fig11_snr_table.json", "fig11_snr_table.csv"):
        assert (a / name).read_bytes() == (b / name).read_bytes(), name


def test_only_keeps_earlier_figures_in_the_index(tmp_path):
    figures.make_figures(tmp_path, quick=True, only=["fig09_gates"], progress=False)
    figures.make_figures(tmp_path, quick=True, only=["fig01_timing"], progress=False)
    names = [e["name"] for e in json.loads((tmp_path / "index.json").read_text())["figures"]]
    assert names == ["fig01_timing", "fig09_gates"]


def test_unknown_figure_is_a_clear_error(tmp_path):
    with pytest.raises(ConfigError, match="--only: unknown figure"):
        figures.make_figures(tmp_path / "x", quick=True, only=["fig99"], progress=False)
    assert not (tmp_path / "x").exists()
    proc = subprocess.run(
        [sys.executable, "-m", "mbcapture", "figures", "--only", "nope", "--out", str(tmp_path / "y")],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert proc.returncode == 2 and "unknown figure" in proc.stderr and proc.stderr.count("\n") == 1


#: Figures of 9 s or more at quick size on 2 cores (2026-11-29): in ``make test-slow``, not ``make test``; their
#: applications' own tests run in both.
SLOW_FIGURES = {
    "hdr_video",
    "fig13_rgb_illumination",
    "structured_light",
    "burst",
    "flutter_shutter",
    "fig16_flash_matting",
    "error_vs_runtime",
    "fig06_interleaving",
}


@pytest.mark.render
@pytest.mark.parametrize(
    "name", [pytest.param(n, marks=pytest.mark.slow) if n in SLOW_FIGURES else n for n in figures.names()]
)
def test_quick_figure_is_written(tmp_path, name):
    """Every figure at quick size (the paper's and the applications'), one test each so that the test
    workers share them out; the slowest in make test-slow."""
    entries = figures.make_figures(tmp_path, quick=True, only=[name], progress=False)
    assert [e["name"] for e in entries] == [name]
    assert all((tmp_path / f).stat().st_size > 0 for f in entries[0]["files"])
    if name == "fig06_interleaving":
        fig6 = json.loads((tmp_path / "fig06_interleaving.json").read_text())["rows"][1:]
        diffs = [r[5] for r in fig6]
        assert diffs[0] > 5 * diffs[-1]  # coarse interleaving ghosts, fine does not
