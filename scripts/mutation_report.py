"""Per-module mutation scores from a mutmut run (the ``mutants/`` folder of scripts/mutation.sh).

Reads mutmut's result files (``mutants/<module>.py.meta``: one exit code per mutant) and prints,
per module and in total: mutants, killed, survived, no tests (no selected test calls the mutated
function), timeouts and other outcomes, and the score (killed + timeout) / (killed + survived +
timeout + other), i.e. over the mutants some selected test runs. ``--survivors`` lists the
surviving mutants with the lines each one changes (mutmut's own diff); ``--json FILE`` writes the
table. Written here because mutmut prints only totals.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from collections import Counter
from pathlib import Path

#: mutmut's exit codes (mutmut/stats.py): 1 and 3 kill, 0 survives, 33 and 5 have no test, the
#: timeout codes come from the CPU-time limit, 37 is "caught by type check" (not configured here).
KILLED = {1, 3, 37}
SURVIVED = {0}
NO_TESTS = {5, 33}
TIMEOUT = {24, -24, 36, 152, 255}


def outcome(code: int | None) -> str:
    if code is None:
        return "not_checked"
    if code in KILLED:
        return "killed"
    if code in SURVIVED:
        return "survived"
    if code in NO_TESTS:
        return "no_tests"
    if code in TIMEOUT:
        return "timeout"
    return "other"


#: Survivor categories (``--survivors``): how a surviving mutant differs from the original. The rules
#: look only at the changed lines; docs/mutation.md says why each category cannot (or need not) be
#: killed, and every "review" survivor of the physics modules is explained there one by one.
CATEGORIES = {
    "message": "only the text of an error message, note or summary line changes",
    "dtype": "only a dtype argument is dropped or set to None (the values arrive in that dtype already)",
    "import_time": "code that runs once at import (registries): mutmut's forked workers never execute the mutant",
    "report_key": "only a key or label of report.json metrics changes (not a computed value)",
    "start_point": "only the starting guess of an exact discrete inversion changes: the walk ends at the same count",
    "review": "none of the above: a test gap, an equivalent mutant or an unreachable branch (see docs/mutation.md)",
}
_IMPORT_TIME = ("x_register__", "x__pymatting__")
_DTYPE = re.compile(
    r",\s*(dtype=)?(np\.(float64|int64)|float|int|bool|None)?\s*(?=[,)])|(?<=\.astype\()(np\.\w+|None|bool)(?=\))"
)


def category(name: str, changed: list[str]) -> str:
    """The :data:`CATEGORIES` key of a surviving mutant from its name and changed lines."""
    if any(k in name for k in _IMPORT_TIME):
        return "import_time"
    if ".x__start__" in name or (
        ".x_binomial_quantile__" in name and any(re.match(r"[-+]\s*(var|sd|guess) =", ln) for ln in changed)
    ):
        return "start_point"
    old = [ln[1:] for ln in changed if ln.startswith("-")]
    new = [ln[1:] for ln in changed if ln.startswith("+")]
    text = " ".join(old)
    if re.search(r"\braise\b|Error\(|summary|\"note\"|warn", text) or (not new and "raise" in text):
        return "message"
    if (
        old
        and new
        and [_DTYPE.sub("", x).replace(" ", "") for x in old] == [_DTYPE.sub("", x).replace(" ", "") for x in new]
    ):
        return "dtype"
    keys_old = re.findall(r'"([^"]*)"\s*:', text)
    keys_new = re.findall(r'"([^"]*)"\s*:', " ".join(new))
    if (
        keys_old
        and keys_new
        and keys_old != keys_new
        and re.sub(r'"[^"]*"\s*:', "", text) == re.sub(r'"[^"]*"\s*:', "", " ".join(new))
    ):
        return "report_key"
    return "review"


def _meta(mutants_dir: Path) -> dict[str, dict]:
    return {
        str(m.relative_to(mutants_dir))[: -len(".meta")]: json.loads(m.read_text())
        for m in sorted(mutants_dir.rglob("*.py.meta"))
    }


def _function(mutant: str) -> str:
    """mutmut's function key of a mutant name (``pkg.mod.x_f__mutmut_3`` -> ``pkg.mod.x_f``)."""
    return mutant.rsplit("__mutmut_", 1)[0]


def load(mutants_dir: Path, baseline: Path | None = None) -> dict[str, dict[str, int | None]]:
    """module path (``mbcapture/sensor/readout.py``) -> mutant name -> exit code.

    ``baseline``: another run's ``mutants/`` folder; a mutant this run left undecided takes the
    baseline's verdict when its function's source hash is the same in both runs (an unchanged
    function with tests that were only added to: killed stays killed). That is how a run of only
    the earlier survivors gives a complete score."""
    metas = _meta(mutants_dir)
    base = _meta(baseline) if baseline else {}
    out = {}
    for module, meta in metas.items():
        codes = dict(meta["exit_code_by_key"])
        old = base.get(module)
        if old:
            same = {
                f
                for f, h in meta.get("hash_by_function_name", {}).items()
                if old.get("hash_by_function_name", {}).get(f) == h
            }
            for name, code in codes.items():
                if code is None and name in old["exit_code_by_key"] and _function(name).split(".")[-1] in same:
                    codes[name] = old["exit_code_by_key"][name]
        if codes:
            out[module] = codes
    return out


def table(results: dict[str, dict[str, int | None]]) -> dict[str, dict]:
    rows = {}
    total = Counter()
    for module, codes in results.items():
        c = Counter(outcome(v) for v in codes.values())
        c["mutants"] = len(codes)
        total.update(c)
        rows[module] = c
    rows["TOTAL"] = total
    for c in rows.values():
        tested = c["killed"] + c["survived"] + c["timeout"] + c["other"]
        c["score"] = round(100.0 * (c["killed"] + c["timeout"]) / tested, 1) if tested else None
    return {m: dict(c) for m, c in rows.items()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mutants", type=Path, default=Path("mutants"), help="mutmut's folder (default: mutants)")
    ap.add_argument("--survivors", action="store_true", help="also list the surviving mutants")
    ap.add_argument("--json", type=Path, help="write the table to this file")
    ap.add_argument(
        "--baseline",
        type=Path,
        help="an earlier run's mutants/ folder: its verdicts fill in the mutants "
        "this run left undecided whose function is unchanged",
    )
    args = ap.parse_args(argv)
    if not args.mutants.is_dir():
        print(f"--mutants: no folder {args.mutants} (run scripts/mutation.sh first)", file=sys.stderr)
        return 2
    results = load(args.mutants, args.baseline)
    rows = table(results)
    cols = ["mutants", "killed", "survived", "no_tests", "timeout", "other", "not_checked"]
    print(f"{'module':44s} " + " ".join(f"{c:>11s}" for c in cols) + "   score %")
    for module, c in rows.items():
        score = "-" if c["score"] is None else f"{c['score']:.1f}"
        print(f"{module:44s} " + " ".join(f"{c.get(k, 0):>11d}" for k in cols) + f"   {score:>7s}")
    if args.survivors:
        from mutmut.mutation.diff_apply import (
            get_diff_for_mutant,  # run from the project root
        )

        counts: dict[str, Counter] = {}
        for module, codes in results.items():
            for name, code in codes.items():
                if outcome(code) in ("survived", "other"):
                    diff = get_diff_for_mutant(name, path=module)
                    changed = [ln for ln in diff.splitlines() if ln[:1] in "+-" and ln[:3] not in ("+++", "---")]
                    cat = category(name, changed)
                    counts.setdefault(module, Counter())[cat] += 1
                    print(f"{outcome(code)} [{cat}]: {name}")
                    print("\n".join(f"    {ln.rstrip()}" for ln in changed))
        print("\nsurvivors by category (" + "; ".join(f"{k}: {v}" for k, v in CATEGORIES.items()) + ")")
        for module, c in counts.items():
            print(f"{module:44s} " + " ".join(f"{k}={c[k]}" for k in CATEGORIES))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
