# The README's quick start: `make capture` and `make test` each set everything up first.
.PHONY: setup capture test test-slow test-budget

setup:
	bash scripts/setup.sh

capture: setup
	.venv/bin/mbcapture run configs/metronome_hdr.yaml --out out/metronome_hdr

# style first (ruff: lint and format, pyproject.toml), then two or more worker processes (pytest-xdist), at most 4:
# renders are multi-threaded already;
# pymatting's numba code compiled once per CPU target first (scripts/warm_numba.py says why)
test: setup
	.venv/bin/ruff check mbcapture scripts tests scenes docs/examples
	.venv/bin/ruff format --check mbcapture scripts tests scenes docs/examples
	.venv/bin/python scripts/warm_numba.py
	.venv/bin/python -m pytest -q -n auto --maxprocesses 4

# the slow checks make test leaves out (3 min 38 s on 2 cores, 2026-11-29): the noise budget measured from outside, the
# goldens on a second CPU target, tiles and a Dask cluster under the noise budget, the shared pattern's statistics,
# killed runs, the resource plan on real runs, the slowest figures
test-slow: setup
	.venv/bin/python scripts/warm_numba.py
	.venv/bin/python -m pytest -q -m slow -n auto --maxprocesses 4

# every shipped config whose samples the noise budget chooses, at 160x128, meets the budget (about 9 minutes
# on 2 cores, two captures at a time, on the Intel Xeon of 2026-11-28: not part of `make test`)
test-budget: setup
	.venv/bin/python -m pytest -q -m budget -n 2 -rP tests/test_budget_configs.py
