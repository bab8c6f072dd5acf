"""``mbcapture design``'s run and outputs: the default, the search and the equal-evaluation grid evaluated, then
written atomically into the output folder:

* ``best.yaml``: the best design as a config ``mbcapture run`` takes;
* ``history.parquet`` (and ``.csv``): every evaluation, its source, values, objectives with their standard
  errors, constraint violation and every measured value;
* ``objective.png``: the objective against each variable; ``pareto.png`` with two objectives;
* ``design.json`` and ``report.html``: the best design against the default and the grid's best, with the
  margins in standard errors.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Callable

import numpy as np


from ..output.htmlparts import esc, figure, table
from ..output.io import staged_outputs
from ..output.plots import design_png, pareto_png
from ..progress import bar
from ..sweep.spec import yaml_value
from .search import Evaluation, Evaluator, best_of, grid_values, search
from .spec import RATIOS_KEY, Design


def _shown(values: dict[str, Any]) -> dict[str, str]:
    return {k: yaml_value(v) for k, v in values.items()}


def history(evals: list[Evaluation]):
    import pandas as pd

    rows = []
    for e in evals:
        rows.append(
            {
                "source": e.source,
                "index": e.index,
                **{f"value.{k}": v for k, v in _shown(e.values).items()},
                "objective": e.objective,
                "objective_se": e.objective_se,
                "second_objective": e.second,
                "second_objective_se": e.second_se,
                "violation": e.violation,
                "feasible": e.feasible,
                "error": e.error,
                "seconds": round(e.seconds, 4),
                **e.row,
            }
        )
    return pd.DataFrame(rows)


def _margin(a: Evaluation | None, b: Evaluation | None, minimize: bool) -> dict | None:
    """How much better ``a`` is than ``b``: the difference (positive = better), relative, in standard errors of the
    two means, and in standard errors of the paired difference (both on the same noise seeds)."""
    if a is None or b is None:
        return None
    diff = (b.objective - a.objective) if minimize else (a.objective - b.objective)
    se = math.hypot(a.objective_se or 0.0, b.objective_se or 0.0)
    out = {
        "better_by": diff,
        "relative": diff / abs(b.objective) if b.objective else None,
        "standard_errors": diff / se if se > 0 else None,
    }
    n = len(a.per_seed)
    if n > 1 and len(b.per_seed) == n:  # the same noise seeds: the paired difference's own standard error
        d = (np.array(b.per_seed) - np.array(a.per_seed)) * (1 if minimize else -1)
        paired = float(np.std(d, ddof=1) / math.sqrt(n))
        out["paired_standard_errors"] = float(d.mean() / paired) if paired > 0 else None
    return out


def pareto_front(evals: list[Evaluation], directions: tuple[str, str]) -> list[Evaluation]:
    """The feasible evaluations no other one beats on both objectives."""
    sign = [1.0 if d == "minimize" else -1.0 for d in directions]
    pts = [e for e in evals if e.feasible and e.second is not None]
    front = []
    for e in pts:
        a = (sign[0] * e.objective, sign[1] * e.second)
        if not any(
            (sign[0] * o.objective <= a[0] and sign[1] * o.second <= a[1])
            and (sign[0] * o.objective < a[0] or sign[1] * o.second < a[1])
            for o in pts
        ):
            front.append(e)
    return front


def _variable_panels(design: Design, evals: list[Evaluation]):
    panels, log_x = [], []
    for key, var in design.spec.variables.items():
        shown = RATIOS_KEY if var.ratios is not None else key

        def x_of(e):
            v = e.values.get(shown)
            return (
                float(max(v)) if var.ratios is not None and v else (float(v) if isinstance(v, (int, float)) else None)
            )

        label = "largest exposure ratio" if var.ratios is not None else key
        sources = []
        for src in ("search", "grid", "default"):
            pts = [(x_of(e), e.objective) for e in evals if e.source == src and e.feasible and x_of(e) is not None]
            if pts:
                sources.append((src, [p[0] for p in pts], [p[1] for p in pts]))
        if sources:
            panels.append((label, sources))
            log_x.append(bool(var.log or var.ratios is not None))
    return panels, log_x


def _row(name: str, e: Evaluation | None) -> list:
    if e is None:
        return [name, "none feasible", "", ""]
    se = f" ± {e.objective_se:.3g}" if e.objective_se else ""
    vals = ", ".join(f"{k}={v}" for k, v in _shown(e.values).items()) or "(the base config)"
    return [name, f"{e.objective:.4g}{se}", vals, f"{e.seconds:.1f} s"]


def report_html(design: Design, doc: dict, best, default, grid_best, pictures: list[str]) -> str:
    spec = design.spec
    rows = [_row("best found", best), _row("default", default), _row("best of the grid", grid_best)]
    margins = "".join(
        f"<p>Best found against {name}: {esc(json.dumps(doc['margins'][key]))}</p>"
        for key, name in (("vs_default", "the default"), ("vs_grid", "the grid at equal evaluations"))
    )
    pics = "".join(figure(p, esc(p), plot=True) for p in pictures)
    return (
        f"<!doctype html><html><head><meta charset='utf-8'><title>mbcapture design {esc(design.name)}</title>"
        f"</head><body><h1>Design: {esc(design.name)}</h1>"
        f"<p>{spec.objective.direction} {esc(spec.objective.metric)} over {len(spec.variables)} variable(s), "
        f"{spec.evaluations} evaluations, {spec.seeds} noise seed(s) each; base {esc(str(design.base))}.</p>"
        + table(rows, ["", "objective (mean ± standard error)", "values", "time"])
        + f"{margins}{pics}</body></html>"
    )


def run_design(design: Design, out: Path, *, progress: bool = True, say: Callable[[str], None] = print) -> dict:
    """Evaluate the default, the search and (``compare_grid``) the grid; write the outputs; return design.json."""
    spec = design.spec
    evaluate = Evaluator(design)
    grid = grid_values(spec.variables, spec.evaluations) if spec.compare_grid else []
    total = 1 + spec.evaluations + len(grid)
    evals: list[Evaluation] = []
    with bar(total=total, desc=f"design {design.name}", unit="design", enabled=progress) as pb:
        evals.append(evaluate("default", 0, {}))
        evals[0].values = design.base_values()  # shown and plotted as the values it has
        pb.update(1)
        evals += search(design, evaluate, on_done=lambda e: pb.update(1))
        for i, values in enumerate(grid):
            evals.append(evaluate("grid", i, values))
            pb.update(1)
    minimize = spec.objective.direction == "minimize"
    found = best_of([e for e in evals if e.source == "search"], spec.objective)
    default = evals[0]
    grid_best = best_of([e for e in evals if e.source == "grid"], spec.objective)
    doc = {
        "spec": str(design.path),
        "base": str(design.base),
        "objective": spec.objective.model_dump(),
        "evaluations": {"search": spec.evaluations, "grid": len(grid), "seeds": spec.seeds},
        "best": None
        if found is None
        else {"values": _shown(found.values), "objective": found.objective, "se": found.objective_se},
        "default": {"objective": default.objective, "se": default.objective_se, "error": default.error},
        "grid_best": None
        if grid_best is None
        else {"values": _shown(grid_best.values), "objective": grid_best.objective, "se": grid_best.objective_se},
        "margins": {
            "vs_default": _margin(found, default if default.feasible else None, minimize),
            "vs_grid": _margin(found, grid_best, minimize),
        },
        "infeasible": sum(1 for e in evals if not e.feasible),
        "seconds": round(sum(e.seconds for e in evals), 2),
    }
    pictures = []
    with staged_outputs(out) as st:
        df = history(evals)
        df.to_parquet(st.path("history.parquet"), index=False)
        df.to_csv(st.path("history.csv"), index=False)
        if found is not None:
            st.write_yaml("best.yaml", design.config(found.values).to_yaml_dict())
        panels, log_x = _variable_panels(design, evals)
        if panels:
            st.write_bytes("objective.png", design_png(panels, spec.objective.metric, log_x))
            pictures.append("objective.png")
        if spec.second_objective is not None:
            front = pareto_front(evals, (spec.objective.direction, spec.second_objective.direction))
            doc["pareto_front"] = [
                {"values": _shown(e.values), "objective": e.objective, "second_objective": e.second} for e in front
            ]
            pts = [
                (
                    src,
                    [e.objective for e in evals if e.source == src and e.feasible],
                    [e.second for e in evals if e.source == src and e.feasible],
                )
                for src in ("search", "grid", "default")
            ]
            st.write_bytes(
                "pareto.png",
                pareto_png(
                    pts,
                    ([e.objective for e in front], [e.second for e in front]),
                    (spec.objective.metric, spec.second_objective.metric),
                ),
            )
            pictures.append("pareto.png")
        st.write_json("design.json", doc)
        st.write_bytes("report.html", report_html(design, doc, found, default, grid_best, pictures).encode("utf-8"))
    if found is not None:
        se = f" ± {found.objective_se:.3g}" if found.objective_se else ""
        say(
            f"best {spec.objective.metric}: {found.objective:.4g}{se} ({', '.join(f'{k}={v}' for k, v in _shown(found.values).items())})"
        )
    for key, name in (("default", "default"), ("grid_best", "best of the grid")):
        d = doc[key]
        if d and d.get("objective") is not None:
            se = f" ± {d['se']:.3g}" if d.get("se") else ""
            say(f"{name}: {d['objective']:.4g}{se}")
    say(f"wrote {out}/report.html, best.yaml, history.parquet")
    return doc
