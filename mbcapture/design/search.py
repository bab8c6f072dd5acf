"""Searching a design spec: each candidate evaluated (a capture on cached renders, several noise seeds; or the
analytic SNR), the optimiser (Optuna's TPE), the equal-evaluation grid and the default, for comparison.

Why Optuna's TPE (and its brute force where every design fits in the budget): the variables mix ranges, log ranges, integers and choices, and the exposure ratios are a
conditional space (how many reads decides how many ratios); TPE models each directly, takes constraints
(a design that breaks one is ranked after every one that keeps them) and two objectives (its Pareto front),
and its draws are seeded. CMA-ES would need a continuous relaxation of the choices.

A candidate's captures share their render stage: every noise seed of a design, and every design whose
render stage is provably the same (:func:`mbcapture.sweep.groups.group_key`: sensor gains, read noise, the
application's keys), runs from one :class:`~mbcapture.capture.pipeline.Rendered` (kept for the last few render
groups); designs that render the same images find them in the render cache.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import time
import warnings
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from ..capture.run import run_capture
from ..errors import ConfigError, MBCaptureError, one_line
from ..studies.dynamic_range import LUMINOUS_EFFICACY_LM_PER_W, analytic, design_of, saturation_radiance, summary
from ..studies.dynamic_range import radiance_grid
from ..sweep.execute import measurements
from ..sweep.groups import group_key
from .spec import RATIOS_KEY, Design, Objective, Variable, ratios_of

#: How many render groups' render stages are kept in memory.
KEEP_RENDERED = 3


@dataclass
class Evaluation:
    """One design evaluated: where it came from (default, search, grid), its variables' values, the mean of each
    measured value over the seeds (``row``), the objectives with their standard errors, whether it keeps the
    constraints, and its error if no capture could be made of it."""

    source: str
    index: int
    values: dict[str, Any]
    row: dict[str, float] = field(default_factory=dict)
    objective: float | None = None
    objective_se: float | None = None
    second: float | None = None
    second_se: float | None = None
    violation: float = 0.0
    error: str | None = None
    seconds: float = 0.0
    #: the objective of each noise seed (the same seeds for every design: differences are paired)
    per_seed: list[float] = field(default_factory=list)

    @property
    def feasible(self) -> bool:
        return self.error is None and self.objective is not None and self.violation <= 0.0


def column(row: dict, name: str) -> str | None:
    """The row's column for a metric name: as given, or under ``metrics.``."""
    for key in (name, f"metrics.{name}"):
        if key in row:
            return key
    return None


class Evaluator:
    """Evaluates designs of one spec (:meth:`__call__`), sharing render stages between them."""

    def __init__(self, design: Design):
        self.design = design
        self.rendered: OrderedDict[str, Any] = OrderedDict()
        self.done: dict[str, Evaluation] = {}  # designs evaluated, by their values

    def _capture_rows(self, values: dict[str, Any]) -> list[dict]:
        rows = []
        for s in range(self.design.spec.seeds):
            cfg = self.design.config({**values, "sensor.noise_seed": 1000 + s})
            key = group_key(cfg)
            kept: dict[str, Any] = {}
            result = run_capture(
                cfg,
                progress=False,
                rendered=self.rendered.get(key),
                on_rendered=None if key in self.rendered else (lambda r: kept.update(rendered=r)),
            )
            if "rendered" in kept:
                self.rendered[key] = kept["rendered"]
                while len(self.rendered) > KEEP_RENDERED:
                    self.rendered.popitem(last=False)
            rows.append({k: v for k, v in measurements(result.report).items() if _number(v)})
        return rows

    def _snr_rows(self, values: dict[str, Any]) -> list[dict]:
        lo, hi = (x / LUMINOUS_EFFICACY_LM_PER_W for x in self.design.spec.evaluator.luminance_cd_m2)
        d = design_of(self.design.config(values))
        sat = saturation_radiance(d)
        # the merge's SNR drops where a read saturates: just above each saturation radiance is a candidate worst
        points = np.unique(np.concatenate([np.geomspace(lo, hi, 400), sat[(sat >= lo) & (sat < hi)] * (1 + 1e-9)]))
        merged = np.nan_to_num(analytic(d, points).merged, nan=0.0)
        full = analytic(d, radiance_grid([d]))
        worst = float(merged.min())
        return [
            {
                "snr.worst_db": 20 * math.log10(max(worst, 1e-10)),  # -200 dB: no usable read somewhere
                "snr.dynamic_range_db": summary(d, full)["dynamic_range_db"],
                "capture_span_s": d.capture_span_s,
            }
        ]

    def __call__(self, source: str, index: int, values: dict[str, Any]) -> Evaluation:
        key = repr(sorted((k, repr(v)) for k, v in values.items()))
        if key in self.done:  # the same design again (a search over few choices proposes it twice): no new captures
            return dataclasses.replace(self.done[key], source=source, index=index, seconds=0.0)
        ev = self._evaluate(source, index, values)
        self.done[key] = ev
        return ev

    def _evaluate(self, source: str, index: int, values: dict[str, Any]) -> Evaluation:
        start = time.perf_counter()
        ev = Evaluation(source, index, values)
        spec = self.design.spec
        try:
            rows = self._capture_rows(values) if spec.evaluator == "capture" else self._snr_rows(values)
        except MBCaptureError as exc:
            ev.error, ev.seconds = one_line(exc), time.perf_counter() - start
            return ev
        keys = set.intersection(*(set(r) for r in rows))
        ev.row = {k: float(np.mean([r[k] for r in rows])) for k in sorted(keys)}
        for obj, attr in ((spec.objective, "objective"), (spec.second_objective, "second")):
            if obj is None:
                continue
            col = column(ev.row, obj.metric)
            if col is None:
                known = sorted(k for k in ev.row if not k.startswith("timings_s"))
                raise ConfigError(
                    f"{self.design.path}: objective {obj.metric!r} is not measured by this capture; it measures "
                    f"{', '.join(known[:40])}{' ...' if len(known) > 40 else ''}"
                )
            vals = [r[col] for r in rows]
            if attr == "objective":
                ev.per_seed = [float(v) for v in vals]
            setattr(ev, attr, float(np.mean(vals)))
            setattr(ev, f"{attr}_se", float(np.std(vals, ddof=1) / math.sqrt(len(vals))) if len(vals) > 1 else 0.0)
        ev.violation = self._violation(ev.row)
        ev.seconds = time.perf_counter() - start
        return ev

    def _violation(self, row: dict) -> float:
        """How far the design is outside its constraints (relative; 0 when it keeps them all)."""
        out = 0.0
        for name, bound in self.design.spec.constraints.items():
            col = column(row, name)
            if col is None:
                raise ConfigError(f"{self.design.path}: constraints: {name!r} is not measured by this capture")
            v = row[col]
            if bound.max is not None and v > bound.max:
                out += (v - bound.max) / max(abs(bound.max), 1e-12)
            if bound.min is not None and v < bound.min:
                out += (bound.min - v) / max(abs(bound.min), 1e-12)
        return out


def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and v is not None and math.isfinite(v)


# ----------------------------------------------------------------------------------- the search
def suggest(trial, variables: dict[str, Variable]) -> dict[str, Any] | None:
    """A design's values drawn by an Optuna trial (None: ratios that coincide)."""
    values: dict[str, Any] = {}
    for key, var in variables.items():
        if var.ratios is not None:
            counts = var.ratios.counts
            n = counts[0] if len(counts) == 1 else trial.suggest_categorical("reads", counts)
            positions = [trial.suggest_float(f"ratio_position_{i}", 0.0, 1.0) for i in range(1, n)]
            ratios = ratios_of(positions, var.ratios.max_ratio)
            if ratios is None:
                return None
            values[RATIOS_KEY] = ratios
            values["sensor.bucket_count"] = n
        elif var.choices is not None:
            values[key] = var.choices[trial.suggest_categorical(key, list(range(len(var.choices))))]
        elif var.integer:
            values[key] = trial.suggest_int(key, math.ceil(var.low), math.floor(var.high), log=var.log)
        else:
            values[key] = sig4(trial.suggest_float(key, var.low, var.high, log=var.log))
    return values


def finite_size(variables: dict[str, Variable]) -> int | None:
    """How many designs the variables allow when every one is a choice or an integer range; None otherwise."""
    n = 1
    for var in variables.values():
        if var.choices is not None:
            n *= len(var.choices)
        elif var.integer and var.ratios is None:
            n *= math.floor(var.high) - math.ceil(var.low) + 1
        else:
            return None
    return n


def axis_size(var: Variable, levels: int) -> int:
    """How many values :func:`grid_values` gives ``var`` at ``levels`` levels, without making them. Ratios: the
    ascending choices of positions whose rounded ratios (:func:`ratios_of`) all differ, i.e. the elementary
    symmetric polynomial of the lengths of the runs of equal rounded ratios."""
    if var.choices is not None:
        return len(var.choices)
    if var.ratios is not None:
        rounded = [float(f"{var.ratios.max_ratio**p:.4g}") for p in np.linspace(0, 1, levels + 1)[1:]]
        runs = [len(list(g)) for r, g in itertools.groupby(rounded) if r > 1.0]
        total = 0
        for n in var.ratios.counts:
            e = [1] + [0] * (n - 1)  # e[j]: ways to take j positions from the runs seen, one a run at most
            for length in runs:
                for j in range(n - 1, 0, -1):
                    e[j] += e[j - 1] * length
            total += e[n - 1]
        return total
    v = np.geomspace(var.low, var.high, levels) if var.log else np.linspace(var.low, var.high, levels)
    return len({int(round(x)) for x in v}) if var.integer else levels


def every_design(variables: dict[str, Variable]) -> list[dict[str, Any]]:
    """Every combination of variables that are all choices or integer ranges."""
    axes = [
        [{k: c} for c in v.choices]
        if v.choices is not None
        else [{k: i} for i in range(math.ceil(v.low), math.floor(v.high) + 1)]
        for k, v in variables.items()
    ]
    return [{k: v for part in combo for k, v in part.items()} for combo in itertools.product(*axes)]


def sig4(x: float) -> float:
    """``x`` to 4 significant digits: a duration or share written so has a coarse exact tick (the timeline's
    common divisor of 0.4372918347 s and 1 ms would need more than 2^62 ticks)."""
    return float(f"{x:.4g}")


def _better(obj: Objective) -> Callable[[float, float], bool]:
    return (lambda a, b: a < b) if obj.direction == "minimize" else (lambda a, b: a > b)


def best_of(evals: list[Evaluation], obj: Objective) -> Evaluation | None:
    """The best feasible evaluation by its mean objective (None if none is feasible)."""
    better = _better(obj)
    best = None
    for e in evals:
        if e.feasible and (best is None or better(e.objective, best.objective)):
            best = e
    return best


def search(
    design: Design, evaluate: Evaluator, on_done: Callable[[Evaluation], None] = lambda e: None
) -> list[Evaluation]:
    """The optimiser's evaluations, in order (``spec.evaluations`` of them)."""
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    spec = design.spec
    objectives = [spec.objective] + ([spec.second_objective] if spec.second_objective else [])
    with warnings.catch_warnings():  # group (the conditional ratios) is marked experimental
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        sampler = optuna.samplers.TPESampler(
            seed=spec.seed, multivariate=True, group=True, n_startup_trials=min(10, max(2, spec.evaluations // 4))
        )
    size = finite_size(spec.variables)
    if size is not None and size <= spec.evaluations:  # every design fits in the budget: try each once
        out_all = []
        for i, values in enumerate(every_design(spec.variables)):
            out_all.append(evaluate("search", i, values))
            on_done(out_all[-1])
        return out_all
    study = optuna.create_study(directions=[o.direction for o in objectives], sampler=sampler)
    out: list[Evaluation] = []
    # one objective: the last share of the budget polishes the best design locally (Nelder-Mead over its ranges)
    continuous = any(v.ratios is not None or (v.choices is None and not v.integer) for v in spec.variables.values())
    polished = continuous and spec.second_objective is None
    n_tpe = max(2, math.ceil(spec.evaluations * (1 - LOCAL_SHARE))) if polished else spec.evaluations
    for i in range(n_tpe):
        trial = study.ask()
        values = suggest(trial, spec.variables)
        if values is None:
            ev = Evaluation("search", i, {}, error="two exposure ratios coincide")
        else:
            ev = evaluate("search", i, values)
        trial.set_constraint("violation", ev.violation if ev.error is None else 1.0)  # <= 0: kept
        if ev.error is not None or ev.objective is None:
            study.tell(trial, state=optuna.trial.TrialState.FAIL)
        else:
            study.tell(trial, [ev.objective] + ([ev.second] if spec.second_objective else []))
        out.append(ev)
        on_done(ev)
    if len(out) < spec.evaluations:
        out += polish(design, evaluate, out, spec.evaluations - len(out), on_done)
    return out


#: The share of a one-objective search's evaluations spent polishing its best design (Nelder-Mead).
LOCAL_SHARE = 0.3


def _unit_axes(variables: dict[str, Variable], values: dict[str, Any]) -> list[tuple[str, Any]]:
    """The continuous dimensions of a design, (key, how to decode a unit value): ranges (log or linear) and the
    exposure ratios' positions; choices and integers stay as they are."""
    axes = []
    for key, var in variables.items():
        if var.ratios is not None:
            n = values.get("sensor.bucket_count", var.ratios.counts[0])
            axes += [(f"{RATIOS_KEY}#{i}", var.ratios.max_ratio) for i in range(1, n)]
        elif var.choices is None and not var.integer:
            axes.append((key, var))
    return axes


def _encode(axes, values: dict[str, Any]) -> np.ndarray:
    u = []
    for key, how in axes:
        if key.startswith(RATIOS_KEY + "#"):
            i = int(key.split("#")[1])
            u.append(math.log(values[RATIOS_KEY][i]) / math.log(how))
        else:
            x, lo, hi = values[key], how.low, how.high
            u.append((math.log(x / lo) / math.log(hi / lo)) if how.log else (x - lo) / (hi - lo))
    return np.clip(np.array(u), 0.0, 1.0)


def _decode(axes, u: np.ndarray, start: dict[str, Any]) -> dict[str, Any] | None:
    values = dict(start)
    positions = []
    for (key, how), x in zip(axes, np.clip(u, 0.0, 1.0)):
        if key.startswith(RATIOS_KEY + "#"):
            positions.append((float(x), how))
        else:
            lo, hi = how.low, how.high
            values[key] = sig4(lo * (hi / lo) ** x if how.log else lo + x * (hi - lo))
    if positions:
        ratios = ratios_of([p for p, _ in positions], positions[0][1])
        if ratios is None:
            return None
        values[RATIOS_KEY] = ratios
    return values


def polish(
    design: Design, evaluate: Evaluator, done: list[Evaluation], budget: int, on_done: Callable[[Evaluation], None]
) -> list[Evaluation]:
    """Up to ``budget`` more evaluations: Nelder-Mead (scipy) from the best feasible design so far, over its
    continuous dimensions in the unit cube, a design outside the constraints or refused scored as the worst."""
    from scipy.optimize import minimize

    spec = design.spec
    best = best_of(done, spec.objective)
    axes = _unit_axes(spec.variables, best.values) if best is not None else []
    out: list[Evaluation] = []
    if best is None or not axes:
        return out
    sign = 1.0 if spec.objective.direction == "minimize" else -1.0

    def f(u: np.ndarray) -> float:
        if len(out) >= budget:
            return math.inf
        values = _decode(axes, u, best.values)
        ev = evaluate("search", len(done) + len(out), values) if values is not None else None
        if ev is None:
            ev = Evaluation("search", len(done) + len(out), {}, error="two exposure ratios coincide")
        out.append(ev)
        on_done(ev)
        return sign * ev.objective if ev.feasible else 1e12

    u0 = _encode(axes, best.values)
    simplex = np.vstack([u0] + [np.clip(u0 + 0.1 * np.eye(len(axes))[i], 0, 1) for i in range(len(axes))])
    minimize(
        f,
        u0,
        method="Nelder-Mead",
        bounds=[(0.0, 1.0)] * len(axes),
        options={"maxfev": budget, "initial_simplex": simplex, "xatol": 1e-5, "fatol": 1e-9},
    )
    return out


def grid_values(variables: dict[str, Variable], budget: int) -> list[dict[str, Any]]:
    """The grid over the same variables with at most ``budget`` designs: the most levels per range (evenly
    spaced, in log where the variable is) that keep the product within the budget; ratios as every ascending
    choice of positions on that many levels."""

    def axis(key: str, var: Variable, levels: int) -> list[dict[str, Any]]:
        if var.choices is not None:
            return [{key: c} for c in var.choices]
        if var.ratios is not None:
            pos = np.linspace(0, 1, levels + 1)[1:]
            out = []
            for n in var.ratios.counts:
                for combo in itertools.combinations(pos, n - 1):
                    r = ratios_of(list(combo), var.ratios.max_ratio)
                    if r is not None:
                        out.append({RATIOS_KEY: r, "sensor.bucket_count": n})
            return out
        if var.log:
            v = np.geomspace(var.low, var.high, levels)
        else:
            v = np.linspace(var.low, var.high, levels)
        if var.integer:
            return [{key: int(x)} for x in sorted({int(round(x)) for x in v})]
        return [{key: sig4(x)} for x in v]

    for levels in range(max(2, budget), 1, -1):  # sizes counted first: the ratios' combinations are many
        if math.prod(axis_size(v, levels) for v in variables.values()) <= budget:
            axes = [axis(k, v, levels) for k, v in variables.items()]
            return [{k: v for part in combo for k, v in part.items()} for combo in itertools.product(*axes)]
    axes = [axis(k, v, 2) for k, v in variables.items()]
    points = [{k: v for part in combo for k, v in part.items()} for combo in itertools.product(*axes)]
    return points[:budget]
