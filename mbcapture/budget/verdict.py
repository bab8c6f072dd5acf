"""The one-line verdict on a run's render error (:func:`noise_verdict`)."""

from __future__ import annotations


import numpy as np

from .quantiles import INTERVAL_COVERAGE


def noise_verdict(render_error: dict, *, adaptive_hint: bool = False) -> str:
    """One sentence: does the rendering's Monte Carlo noise matter next to the photon shot noise?
    Judged on the budget (``render_error.budget``: the median and 95th percentile of the per-sample
    Monte Carlo / shot-noise variance ratio of the deciding read against render.noise_budget and
    render.noise_budget_p95), with the tail (99.9th percentile) against render.noise_budget_tail.
    ``adaptive_hint``: a run that could have sampled adaptively and did not; a tail over its target
    then points to render.adaptive."""
    med, p95 = render_error.get("to_shot_noise_variance_median"), render_error.get("to_shot_noise_variance_p95")
    budget = render_error.get("budget")
    if med is None or budget is None:
        return f"Not estimated: {render_error.get('note', 'no half-sample estimate')}."
    extra = 100 * (np.sqrt(1 + med) - 1)  # added to the median sample's noise standard deviation
    where = f" of read {render_error['deciding_read']}" if "deciding_read" in render_error else ""
    level = (
        f"rendering noise variance is {med:.3g} x the shot-noise variance in the median sample{where} and "
        f"{p95:.3g} x in the 95th percentile (budget {budget['median_target']:g} / {budget['p95_target']:g})"
    )
    tail = render_error.get("to_shot_noise_variance_p999")
    tail_iv = render_error.get("to_shot_noise_variance_p999_interval")
    within = "" if tail_iv is None else f", {INTERVAL_COVERAGE:.0%} interval {tail_iv[0]:.3g}-{tail_iv[1]:.3g}"
    tail_text = ""
    if tail is not None and "tail_target" in budget:
        target = f"render.noise_budget_tail {budget['tail_target']:g}"
        # over by the estimate with an interval reaching below the target: the run cannot tell (after adaptive
        # sampling the unrefined film's tail rests on a few audit blocks; docs/noise.md)
        if budget.get("tail_met"):
            judged = f"within {target}"
        elif tail_iv is None or tail_iv[0] > budget["tail_target"]:
            judged = f"over {target}"
        else:
            judged = f"over {target} by this estimate, but its interval reaches below it: the run cannot tell"
        tail_text = f" Tail: {tail:.3g} x in the 99.9th percentile{within} ({judged})."
    if tail_text and adaptive_hint and not budget.get("tail_met"):
        tail_text += " render.adaptive: true renders the pixels over it again (docs/noise.md)."
    if budget["met"]:
        return f"Sensor noise dominates: {level}, adding {extra:.1f} % to the median sample's noise.{tail_text}"
    head = (
        f"Rendering noise is visible in the simulated images: {level}, adding {extra:.0f} % to the median "
        "sample's noise; "
    )
    spp = f"render.spp >= {budget['spp_that_would_meet']}" if "spp_that_would_meet" in budget else None
    if budget.get("spp_source") == "noise_budget":  # the pilot's estimate missed: more samples, not the budget again
        return (
            head
            + (
                f"the noise budget's pilot under-estimated it; {spp} would meet it."
                if spp
                else "the noise budget's pilot under-estimated it."
            )
            + tail_text
        )
    return head + (f"{spp} or " if spp else "") + "render.spp: null (the noise budget) would meet it." + tail_text
