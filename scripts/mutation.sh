#!/usr/bin/env bash
# Mutation testing of the physics modules with mutmut (docs/mutation.md): mbcapture/sensor/,
# mbcapture/reconstruct/, mbcapture/timing/timeline.py and mbcapture/apps/, against the fast pure-numpy
# tests (no renders, no goldens; the selection is [tool.mutmut] in pyproject.toml).
#
#   scripts/mutation.sh                                # every mutant not yet decided (first run: all)
#   scripts/mutation.sh 'mbcapture.sensor.readout.*'   # these mutants again (names or globs)
#   JOBS=1 scripts/mutation.sh                         # one worker (default 2)
#
# Results stay in mutants/ (ignored by git): a second run only tests what is undecided, and
# `.venv/bin/mutmut show NAME` prints a mutant's diff. Scores per module are printed at the end
# (scripts/mutation_report.py; also written to mutants/scores.json). Delete mutants/ after
# changing tests to score them afresh.
set -euo pipefail
cd "$(dirname "$0")/.."
if [ ! -x .venv/bin/mutmut ]; then
  bash scripts/setup.sh
  .venv/bin/python -m pip install -q --disable-pip-version-check -e '.[test,mutation]'
fi
# mutmut forks one worker per mutant from a process that has run the tests: numba's default
# OpenMP threading layer (pymatting) terminates a forked child ("fork() called from a process
# already using GNU OpenMP"), its workqueue layer does not.
export NUMBA_THREADING_LAYER=workqueue
start=$(date +%s)
.venv/bin/mutmut run --max-children "${JOBS:-2}" "$@"
echo "mutation.sh: $(( $(date +%s) - start )) s"
.venv/bin/python scripts/mutation_report.py --json mutants/scores.json
