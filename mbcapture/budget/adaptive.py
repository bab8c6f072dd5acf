"""Adaptive sampling and the top-up: the render passes after the first, where the run's own estimate says
the first pass fell short of the noise budget (docs/noise.md).

:func:`after_first_pass` is the sequence a capture runs: adaptive sampling's choice of pixels
(:func:`scout_tail`), the budget's top-up (:func:`top_up`, judged on the image those pixels will give),
their refinement (:func:`refine_tail`) and a second round where the tail is still over its target
(:func:`second_round`). What every pass shares (the config, the renderer, the timeline, the seed, the
status line, the film's tiles) is one :class:`Passes`.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, replace
from typing import Any, Callable

import numpy as np

from ..config import CaptureConfig
from ..exposure import resources
from ..exposure.integrate import WHOLE_FILM, FilmLayout, Integrated, refine, sample_counter
from ..exposure.plan import Plan
from ..progress import StageStatus
from ..sensor import electrons_per_render_second
from ..timing.timeline import Timeline
from .error import BucketElectrons, render_error
from .tiers import TailModel, scout_spp, tail_pixels


@contextmanager
def _untimed(name: str):
    yield


@dataclass
class Passes:
    """What every render pass after the first shares: the capture's ``cfg``, ``renderer``, ``timeline`` and
    render ``seed`` (each pass spawns its own from it), the ``status`` line, a ``timer`` (``timer(name)``: a
    context that adds its time to a stage of report.json's timings), a progress bar or not, whether the
    application needs per-group exposures, the film's ``layout`` (its tiles and where whole-film results
    live) and ``changing``: (H, W) where a render's time within its stratum is noise
    (:func:`mbcapture.render.shadows.changing_region`)."""

    cfg: Any
    renderer: Any
    timeline: Timeline | None
    seed: np.random.SeedSequence | None
    status: StageStatus
    timer: Callable[[str], Any] = _untimed
    progress: bool = False
    per_group: bool = False
    layout: FilmLayout = WHOLE_FILM
    changing: np.ndarray | None = None


def after_first_pass(
    passes: Passes, plan: Plan, integrated: Integrated
) -> tuple[Plan, Integrated, dict | None, dict | None]:
    """The passes after the first (``render.spp`` null): adaptive sampling's choice (``render.adaptive``),
    the top-up (``render.top_up``), the refinement and its second round. Returns the plan (with the top-up's
    samples), the render stage, and what report.json keeps of adaptive sampling and of the top-up."""
    cfg = passes.cfg
    tiers, adaptive_info, planned_reads = None, None, None
    if cfg.render.adaptive:
        tiers, adaptive_info, planned_reads = scout_tail(passes, plan, integrated)
    top_up_info = None
    if cfg.render.top_up:
        why_not = "render.estimator independent" if plan.estimator != "independent" else None
        tail = bool(adaptive_info and adaptive_info.get("rules_judged") and not adaptive_info["tail_met_by_rule"])
        plan, integrated, top_up_info = top_up(
            passes, plan, integrated, why_not=why_not, planned=tiers, planned_reads=planned_reads, tail=tail
        )
    if tiers:
        passes.status.continued()  # the scout's stage was counted at the start; its refinement is a part of it
        integrated, adaptive_info = refine_tail(passes, plan, integrated, tiers, adaptive_info)
        integrated, adaptive_info = second_round(passes, plan, integrated, tiers, adaptive_info)
    return plan, integrated, adaptive_info, top_up_info


#: The top-up aims this far under the budget (the run's own estimate scatters from seed to seed), and
#: sizes its pass for the less favourable of variance ~ 1/spp and ~ spp^-TOP_UP_EXPONENT (the steep
#: end of what the pilot sees): a pass with fewer samples than the first is dearer per sample with
#: quasi-Monte Carlo samplers, one with more gains less than their exponent promises.
TOP_UP_MARGIN = 1.1
TOP_UP_EXPONENT = 1.5


def read_figures(
    integrated: Integrated,
    timeline: Timeline,
    cfg: CaptureConfig,
    names: list[str] | None = None,
    plan: Plan | None = None,
) -> dict:
    """The run's own estimate of each read's rendering noise (render_error's ``reads``), of the reads
    ``names`` (default: all); with ``plan``, of the channel sets it reads (:attr:`Plan.read_sets`: a coded
    capture's render stage holds sub-frames, not buckets), else of the timeline's reads' buckets."""
    k_e = electrons_per_render_second(cfg.sensor, cfg.render.variant)
    sets = (
        list(zip(plan.read_names, plan.read_sets))
        if plan is not None
        else [(r.name, r.buckets) for r in timeline.reads]
    )
    sets = [(n, b) for n, b in sets if names is None or n in names]
    return render_error(
        integrated.mc_diff,
        BucketElectrons(integrated.exposure, k_e),
        k_e,
        [b for _, b in sets],
        [n for n, _ in sets],
        cfg.sensor.full_well_e,
        cfg.sensor.fd_full_well_e,
    ).get("reads", {})


def over_budget(
    integrated: Integrated,
    timeline: Timeline,
    cfg: CaptureConfig,
    reads: dict | None = None,
    *,
    tail: bool = False,
    plan: Plan | None = None,
) -> tuple[float, str | None, str, float]:
    """How far the run's own estimate of its rendering noise is over the budget's median and p95 targets
    (render.noise_budget, render.noise_budget_p95), and with ``tail`` its tail target too
    (render.noise_budget_tail), on its worst read: (max over reads of each figure over its target, that
    read, the figure that decides it (render_error's ``to_shot_noise_variance_median``, ``_p95`` or
    ``_p999``), its value); (0, None, "", 0) without an estimate. ``reads``: :func:`read_figures` of
    ``integrated`` where they are at hand, else made here (with ``plan``, on its channel sets: a coded capture's)."""
    reads = read_figures(integrated, timeline, cfg, plan=plan) if reads is None else reads
    if not reads:
        return 0.0, None, "", 0.0
    targets = {
        "to_shot_noise_variance_median": cfg.render.noise_budget,
        "to_shot_noise_variance_p95": cfg.render.noise_budget_p95,
        **({"to_shot_noise_variance_p999": cfg.render.noise_budget_tail} if tail else {}),
    }
    over = {(n, k): v[k] / t for n, v in reads.items() for k, t in targets.items()}
    worst, key = max(over, key=over.get)
    return over[(worst, key)], worst, key, reads[worst][key]


def no_room_for_another_pass(integrated: Integrated, layout: FilmLayout = WHOLE_FILM) -> str | None:
    """Why another render pass over the film cannot run here, or None: it holds a second set of the
    film's arrays while it renders (two float64 halves of each, its per-group and temporal sums), which
    must fit in free memory beside what the run holds (the top-up's second pass, adaptive sampling's
    scout). In tiles (``layout``) the pass holds that for its largest tile, and its results are whole-film
    arrays beside them unless they go to scratch files."""
    arrays = [
        a
        for a in (integrated.exposure, integrated.mc_diff, integrated.group_exposure, integrated.temporal_diff)
        if a is not None
    ]
    share = layout.tile_share(integrated.exposure.shape[-3])
    results = 0.0 if share == 1.0 or layout.store.spills else 1.0
    need = int((3 * share + results) * sum(a.size * 8 for a in arrays))
    free, where = resources.free_memory()
    if need <= free - resources.rss_bytes():
        return None
    return (
        f"room for a second set of the film's arrays ({need / 1e9:.2f} GB; "
        f"{max(free - resources.rss_bytes(), 0) / 1e9:.2f} GB free by {where})"
    )


def top_up(
    passes: Passes,
    plan: Plan,
    integrated: Integrated,
    *,
    why_not: str | None,
    planned: list[tuple[np.ndarray, int]] | None = None,
    planned_reads: dict | None = None,
    tail: bool = False,
) -> tuple[Plan, Integrated, dict | None]:
    """render.top_up: when the pilot's choice left the run's own estimate over the median or p95 target
    (:func:`over_budget` > 1; the pilot extrapolates from 8 and 32 samples, and its exponent can be
    too steep for the count it reaches), or, after adaptive sampling's choice, over the tail target (where
    none of its rules brings the tail under it: a first pass of few samples whose rare paths the scout,
    at fewer still, did not see), a second pass of every stratum, combined with the first.
    ``planned``: adaptive sampling's tiers (:func:`scout_tail`), still to be rendered: the budget is judged
    on the image they will give (:func:`with_planned_refinement`; ``planned_reads``: its :func:`read_figures`,
    where :func:`scout_tail` made them), the one the run returns; ``tail``: the tail target judged too (where
    adaptive sampling judged its rules and none met it). (Judged before
    them, a first pass a hair over the median target, 1.008x, took a top-up of 12 % more samples on the
    default capture, which its refined pixels would have brought under the target anyway.)

    The second pass and its weight: :func:`combine_passes`. The second pass goes through the film as the first did (``layout``: its
    tiles, and where its results are made). Returns the plan with the summed samples, the combined render stage
    and what report.json keeps (None when the first pass met the budget)."""
    if integrated.mc_diff is None:
        return plan, integrated, None
    factor, worst, figure, _ = over_budget(
        with_planned_refinement(integrated, planned or []),
        passes.timeline,
        passes.cfg,
        planned_reads,
        tail=tail,
        plan=plan,
    )
    if factor <= 1.0:
        return plan, integrated, None
    why_not = why_not or no_room_for_another_pass(integrated, passes.layout)
    if why_not is not None:
        return (
            plan,
            integrated,
            {"applied": False, "before": round(factor, 4), "note": f"not applied: a top-up needs {why_not}"},
        )
    passes.status.continued()
    with passes.status.stage(f"top-up render (the estimate is {factor:.2f}x the noise budget)"):
        start = time.perf_counter()
        extra = top_up_samples(passes, plan, factor)
        if isinstance(extra, str):  # the second pass must render every stratum: its exposure is the
            # combination's only where it holds all of them (a stratum left out would be missing, not less noisy)
            return plan, integrated, {"applied": False, "before": round(factor, 4), "note": extra}
        extend = plan.shares_pattern
        child = np.random.SeedSequence(passes.seed.entropy, spawn_key=(*passes.seed.spawn_key, 0x70F))
        rng = np.random.default_rng(
            np.random.SeedSequence(passes.seed.entropy, spawn_key=(*passes.seed.spawn_key, 0x70F, 0x7))
        )
        times = plan.draw_times(rng)[:, :, 0]
        second_plan = replace(plan, spp=extra, times_s=times[:, 0], half_times_s=times)
        second = passes.layout.integrate(
            passes.renderer,
            second_plan,
            passes.timeline.n_channels,
            child,
            per_group=passes.per_group,
            timer=passes.timer,
            progress=passes.progress,
            desc="top-up",
            continues=(plan, passes.seed) if extend else None,
        )
        plan, integrated, c = combine_passes(passes, plan, integrated, second, second_plan, worst, figure)
        info = {
            "applied": True,
            "before": round(factor, 4),
            "read": worst,
            "figure": figure.removeprefix("to_shot_noise_variance_"),
            "spp_added": extra.tolist(),
            "weight": round(c, 4),
            "after": round(
                over_budget(
                    with_planned_refinement(integrated, planned or []),
                    passes.timeline,
                    passes.cfg,
                    tail=tail,
                    plan=plan,
                )[0],
                4,
            ),
            "judged_with_refinement": bool(planned),
            "seconds": round(time.perf_counter() - start, 3),
        }
    return plan, integrated, info


def top_up_samples(passes: Passes, plan: Plan, factor: float) -> np.ndarray | str:
    """(J,) the top-up's samples per stratum for a first pass ``factor`` over the budget, at most render.max_spp in
    all, or why it cannot run (a stratum with no room left)."""
    count = sample_counter(passes.renderer, plan)
    # with the shared pattern the second pass continues each pixel's sequences after the first's, and
    # the two weighed by their samples are one pass of n1 + n2: variance at least as 1 / spp, so
    # (n1 + n2) / n1 = F x margin. An independent second pass needs V1 / V2 = F x margin - 1, and a
    # smaller pass is dearer per sample (TOP_UP_EXPONENT)
    gap = factor * TOP_UP_MARGIN - 1.0
    share = gap if plan.shares_pattern else max(gap ** (1.0 / TOP_UP_EXPONENT), gap)  # n2 / n1
    extra = np.array([2 * count(max(int(np.ceil(share * n / 2)), 1)) for n in plan.spp], np.int64)
    room = np.maximum(passes.cfg.render.max_spp - plan.spp, 0) // 2 * 2  # two halves of whole samples
    if (room < 2).any():
        return f"render.max_spp={passes.cfg.render.max_spp} reached in {int((room < 2).sum())} of {plan.passes} strata"
    return np.minimum(extra, room)


def combine_passes(
    passes: Passes, plan: Plan, first: Integrated, second: Integrated, second_plan: Plan, worst: str, figure: str
) -> tuple[Plan, Integrated, float]:
    """The first pass and the top-up's ``second`` (rendered at ``second_plan``) as one render stage,
    ``(E1 + c E2) / (1 + c)``: ``c`` by their samples where the second continues the first's pattern, else by
    the inverse of the read ``worst``'s ``figure`` in each; returns the plan with the summed samples and the times
    the combined exposure holds, the combined stage and ``c``."""
    extra = second_plan.spp
    times = second_plan.half_times_s
    c = float(extra.sum() / plan.spp.sum())  # by their samples: each sample alike when they continue
    if not plan.shares_pattern:  # the two passes' figures as rendered (the planned refinement adds to both alike)
        v1, v2 = (
            read_figures(x, passes.timeline, passes.cfg, [worst], plan=plan).get(worst, {}).get(figure, 0.0)
            for x in (first, second)
        )
        c = v1 / v2 if v2 > 0 else c

    def mix(a: np.ndarray | None, b: np.ndarray | None) -> np.ndarray | None:
        return None if a is None or b is None else passes.layout.mix(a, b, c)

    combined = Integrated(
        exposure=mix(first.exposure, second.exposure),
        mc_diff=mix(first.mc_diff, second.mc_diff),
        group_exposure=mix(first.group_exposure, second.group_exposure),
        temporal_diff=mix(first.temporal_diff, second.temporal_diff),
    )
    # the exposure's times: the first pass's at weight 1 / (1 + c), the second's at c / (1 + c)
    t1, w1 = plan.exposure_time_mix()
    plan = replace(
        plan,
        spp=plan.spp + extra,
        mix_times_s=np.concatenate([t1, times], axis=1),
        mix_weights=np.concatenate([w1, c * second_plan.render_time_shares()], axis=1) / (1.0 + c),
    )
    return plan, combined, c


#: Adaptive sampling renders each half of a stratum at this many times (one in each equal part of the
#: stratum) where a render's time is noise (the moving parts, their shadows, a moving camera's film): the value
#: changes within a stratum there, and one time per half leaves that change as noise more samples do not lower (jittered, its variance falls
#: as 1 / points^3 for an edge moving at constant speed); elsewhere at one time, which keeps each
#: render's samples together (the quasi-Monte Carlo samplers stratify within a render).
REFINE_TIME_POINTS = 4


def scout_tail(
    passes: Passes,
    plan: Plan,
    integrated: Integrated,
    *,
    have: np.ndarray | None = None,
    max_factor: int | None = None,
) -> tuple[list[tuple[np.ndarray, int]] | None, dict, dict | None]:
    """Adaptive sampling's choice (render.adaptive): a scout, the strata rendered again with seeds of their own
    at about a sixteenth of the first pass's samples (:func:`mbcapture.budget.scout_spp`), chooses the pixels
    whose predicted ratio (the scout's, scaled as 1/spp except in ``passes.changing``, where a render's time is noise:
    :func:`mbcapture.render.shadows.changing_region`) exceeds
    a level x the tail target (:func:`mbcapture.budget.tail_pixels`), each with the factor of the first pass's
    samples it is to have. The rule, a level of budget.ADAPTIVE_LEVELS and a most factor, is the cheapest whose
    factors bring the run's own estimate of the tail, on the first pass as they will leave it
    (:func:`with_planned_refinement`; :class:`mbcapture.budget.TailModel`), under render.noise_budget_tail.
    Which pixels are chosen is independent of the first pass, and the rule is one choice from the whole film's
    estimate, so every pixel's estimate, and the run's own estimate of its error, is unbiased. Made before the top-up, which judges the budget on the image these factors will give
    (:func:`top_up`), and rendered after it (:func:`refine_tail`). Returns the tiers (None where adaptive
    sampling cannot apply), what report.json keeps and the chosen tiers' :func:`read_figures` (what the top-up
    judges on). The scout goes through the film as the first pass did (``layout``); the choice is made on the
    whole film's arrays.

    ``have`` (flat, per pixel): a second round (:data:`ADAPTIVE_ROUNDS`), on a render stage already refined to these
    factors of the first pass's samples: the scout (seeds of its own again) is scaled to them, the rule judged on
    that stage's own estimate, and the tiers are factors of what each pixel holds, at most ``max_factor`` (default
    render.adaptive_max_factor)."""
    why = (
        "render.estimator independent"
        if plan.estimator != "independent"
        else "two half-sample renders per stratum (spp >= 2)"
        if integrated.mc_diff is None
        else no_room_for_another_pass(integrated, passes.layout)
    )  # the scout renders the film again
    if why is not None:
        return None, {"pixels": 0, "note": f"not applied: adaptive sampling needs {why}"}, None
    with passes.status.stage("adaptive sampling: scout"):
        start = time.perf_counter()
        k_e = electrons_per_render_second(passes.cfg.sensor, passes.cfg.render.variant)
        spp = np.asarray(plan.spp, np.int64)
        scout_plan, scout = render_scout(passes, plan, again=have is not None)
        # the first pass's ratio over the scout's: as 1/spp where nothing moves; 1 where a render's time is noise,
        # as there both passes draw one time per half-stratum, and their time noise does not fall with samples
        scale = np.where(passes.changing, 1.0, float((scout_plan.spp / np.maximum(spp, 1)).max()))
        if have is not None:  # and over the factors the pixels hold
            scale = scale / have.reshape(scale.shape)
        on_moving = passes.changing.ravel()
        with passes.timer("adaptive_rule"):  # the tail each rule would leave, from the first pass's own estimate
            model = TailModel(
                integrated.mc_diff,
                BucketElectrons(integrated.exposure, k_e),
                k_e,
                list(plan.read_sets),
                passes.cfg.sensor.full_well_e,
                passes.cfg.sensor.fd_full_well_e,
                passes.cfg.render.noise_budget_tail,
            )
        tried = []

        def meets(factors: np.ndarray) -> bool:
            tried.append(model.meets(factors))
            return tried[-1]

        tiers = tail_pixels(
            scout.mc_diff,
            BucketElectrons(scout.exposure, k_e),
            k_e,
            list(plan.read_sets),
            passes.cfg.sensor.full_well_e,
            passes.cfg.sensor.fd_full_well_e,
            passes.cfg.render.noise_budget_tail,
            max_factor or passes.cfg.render.adaptive_max_factor,
            scale,
            meets=meets,
            changing=on_moving,
        )
        with passes.timer("adaptive_rule"):  # the run's own estimate on the image the tiers will give: the top-up's too
            planned = read_figures(with_planned_refinement(integrated, tiers), passes.timeline, passes.cfg, plan=plan)
        n_pix = sum(p.size for p, _ in tiers)
        film = passes.cfg.render.width * passes.cfg.render.height
        held = np.ones(film, np.int64) if have is None else have
        info = {
            "scout": {"spp": scout_plan.spp.tolist(), "seconds": round(time.perf_counter() - start, 3)},
            "pixels": int(n_pix),
            "share": round(n_pix / film, 6),
            "tiers": [{"factor": f, "pixels": int(p.size), "moving_pixels": int(on_moving[p].sum())} for p, f in tiers],
            # the second pass's samples over the first pass's, on the whole film
            "added_samples": round(sum(int(held[p].sum()) * (f - 1) for p, f in tiers) / film, 4),
        }
        # how many rules were judged, and the tail the run's own estimate predicts for the one kept
        info.update(
            rules_judged=len(tried),
            tail_met_by_rule=bool(tried and tried[-1]),
            predicted_tail=round(max((v["to_shot_noise_variance_p999"] for v in planned.values()), default=0.0), 4),
        )
    return tiers, info, planned


def render_scout(passes: Passes, plan: Plan, *, again: bool = False) -> tuple[Plan, Integrated]:
    """Adaptive sampling's scout: the strata rendered again at about a sixteenth of the first pass's samples
    (:func:`mbcapture.budget.tiers.scout_spp`) with seeds of their own (``again``: a second round's, of their own
    again), through the film as the first pass went. Returns its plan and its render stage."""
    scout_plan = replace(plan, spp=scout_spp(np.asarray(plan.spp, np.int64), sample_counter(passes.renderer, plan)))
    key = (0x2D,) if again else ()
    with passes.timer("scout"):
        scout = passes.layout.integrate(
            passes.renderer,
            scout_plan,
            passes.timeline.n_channels,
            np.random.SeedSequence(passes.seed.entropy, spawn_key=(*passes.seed.spawn_key, 0x5C0, *key)),
            progress=passes.progress,
            desc="scout again" if again else "scout",
        )
    return scout_plan, scout


def with_planned_refinement(integrated: Integrated, tiers: list[tuple[np.ndarray, int]]) -> Integrated:
    """``integrated`` with the error estimate it will have once adaptive sampling has given each pixel of
    ``tiers`` its factor f of the samples: the half-sample differences over sqrt(f) there (variance ~ 1/spp,
    as :func:`mbcapture.budget.factor_tiers` assumes; scripts/adaptive_frontier.py measured the tail so
    predicted within 1 %). What the top-up judges the budget on, as the image the run returns will have it."""
    if not tiers or integrated.mc_diff is None:
        return integrated
    K, H, W, C = integrated.mc_diff.shape
    shrink = np.ones(H * W, np.float32)
    for pixels, factor in tiers:
        shrink[pixels] = 1.0 / np.sqrt(factor)
    return replace(integrated, mc_diff=integrated.mc_diff * shrink.reshape(1, H, W, 1))


def refine_tail(
    passes: Passes,
    plan: Plan,
    integrated: Integrated,
    tiers: list[tuple[np.ndarray, int]],
    info: dict,
    *,
    have: np.ndarray | None = None,
) -> tuple[Integrated, dict]:
    """Adaptive sampling's second pass (render.adaptive): the pixels of :func:`scout_tail`'s ``tiers`` rendered
    again with more samples and added to the first pass (:func:`mbcapture.exposure.integrate.refine`), those in
    ``passes.changing`` (where a render's time is noise, :func:`mbcapture.render.shadows.changing_region`) at
    :data:`REFINE_TIME_POINTS` times per half-stratum. A
    top-up between the two keeps the tiers (chosen for the first pass's samples, they then give a little more
    than they need: the top-up lowered every pixel's ratio). Returns the refined render stage and what
    report.json keeps (``info``, the scout's, completed). ``have``: a second round's (:func:`scout_tail`), the
    tiers' factors then of what each pixel holds."""
    with passes.status.stage("adaptive sampling: refine"):
        start = time.perf_counter()
        pixels = np.concatenate([p for p, _ in tiers])
        held = np.ones(pixels.size, np.int64) if have is None else have[pixels]
        factors = held * np.concatenate([np.full(p.size, f, np.int64) for p, f in tiers])
        on_moving = passes.changing.ravel()[pixels]
        again = () if have is None else (0x2D,)
        for part, points in ((~on_moving, 1), (on_moving, REFINE_TIME_POINTS)):  # every tier at once
            if part.any():
                child = np.random.SeedSequence(
                    passes.seed.entropy, spawn_key=(*passes.seed.spawn_key, 0xADA, points, *again)
                )
                integrated = refine(
                    passes.renderer,
                    plan,
                    integrated,
                    pixels[part],
                    factors[part],
                    child,
                    points=points,
                    per_group=passes.per_group,
                    timer=passes.timer,
                    progress=passes.progress,
                    have=held[part],
                    desc=f"refine {int(part.sum())} px" + (" moving" if points > 1 else ""),
                    store=passes.layout.store,
                )
        info["seconds"] = round(info["scout"]["seconds"] + time.perf_counter() - start, 3)
    return integrated, info


#: The most rounds of adaptive sampling: a second where the first's refined render stage still has its own estimate
#: of the tail over its target (the rule is judged on the first pass's estimate divided by the factors, and the pixels that draw
#: rare paths of their own in the second pass are not in it), with a scout of its own, at most
#: :data:`SECOND_ROUND_MAX_FACTOR` times what each pixel holds. Measured on multi_flash at 160x128: a rule judged to leave 0.95 left 1.13, the 68 samples over the target (61 allowed) at static
#: silhouettes given 16-32x and at the rim of the changing region.
ADAPTIVE_ROUNDS = 2
SECOND_ROUND_MAX_FACTOR = 4


def second_round(
    passes: Passes, plan: Plan, integrated: Integrated, tiers: list[tuple[np.ndarray, int]], info: dict
) -> tuple[Integrated, dict]:
    """Adaptive sampling's second round (:data:`ADAPTIVE_ROUNDS`), where the refined render stage's own estimate of
    the tail is still over render.noise_budget_tail on some read (the median and p95 are the top-up's):
    :func:`scout_tail` and :func:`refine_tail` again, from what each pixel holds. Unbiased as the first round is: its
    pixels come from a scout of its own, its rule from the whole film's estimate, and whether it runs from the whole
    film's. Returns the render stage and ``info``, with ``second_round`` where one ran."""
    reads = read_figures(integrated, passes.timeline, passes.cfg, plan=plan)
    factor = (
        max((v["to_shot_noise_variance_p999"] for v in reads.values()), default=0.0)
        / passes.cfg.render.noise_budget_tail
    )
    if ADAPTIVE_ROUNDS < 2 or factor <= 1.0:
        return integrated, info
    film = passes.cfg.render.width * passes.cfg.render.height
    have = np.ones(film, np.int64)
    for pixels, f in tiers:
        have[pixels] = f
    passes.status.continued()
    more, round_info, _ = scout_tail(passes, plan, integrated, have=have, max_factor=SECOND_ROUND_MAX_FACTOR)
    round_info["before"] = round(factor, 4)
    if more:
        passes.status.continued()
        integrated, round_info = refine_tail(passes, plan, integrated, more, round_info, have=have)
    info["second_round"] = round_info
    return integrated, info
