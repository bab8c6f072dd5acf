# The README's quick start: `make capture` and `make test` each set everything up first.
.PHONY: setup capture test

setup:
	bash scripts/setup.sh

capture: setup
	.venv/bin/mbcapture run configs/metronome_hdr.yaml --out out/metronome_hdr

test: setup
	.venv/bin/python -m pytest -q
