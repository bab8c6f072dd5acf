"""The render plan: time strata chosen by image motion, and exact gate x emitter weights.

The bucket images are  B_k = integral gate_k(t) * sum_g drive_g(t) * L_g(geometry(t)) dt.
Gates and flashes switch thousands of times, geometry moves slowly: the planner cuts the
collecting time into strata inside which no moving point travels more than
``render.max_motion_px`` pixels, renders each stratum once at a jittered time, and integrates
gate x drive analytically (:meth:`Timeline.weights_ticks`). A static scene is one stratum
however many buckets, flashes and periods there are.

Left out: emitter groups with no weight in any read bucket, buckets never read, strata with
no weight at all.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .config import RenderSection
from .errors import ConfigError
from .scenes import SceneModel
from .timeline import Timeline

#: Motion is sampled this finely (per collecting interval) to bound image motion.
_MOTION_SAMPLES = 4096


@dataclass(frozen=True)
class Plan:
    """What will be rendered.

    starts_ticks, ends_ticks   (J,) stratum bounds [start, end), int64 ticks.
    times_s       (J,) scene time at which each stratum is rendered (jittered inside it).
    weights_s     (J, K, G) seconds of stratum j in which bucket k collects while group g is on.
    groups        the emitter groups rendered (G), in the scene's order.
    """

    starts_ticks: np.ndarray
    ends_ticks: np.ndarray
    times_s: np.ndarray
    weights_s: np.ndarray
    groups: tuple[str, ...]
    buckets_read: tuple[int, ...]
    spp: int
    max_motion_px: float
    motion_px_total: float
    coarsened: bool
    left_out_groups: tuple[str, ...]
    notes: list[str] = field(default_factory=list)

    @property
    def passes(self) -> int:
        return len(self.times_s)

    def summary(self, timeline: Timeline) -> dict:
        return {
            "passes": self.passes,
            "spp": self.spp,
            "samples_per_pixel_total": self.passes * self.spp,
            "groups_rendered": list(self.groups),
            "groups_left_out": list(self.left_out_groups),
            "buckets_read": [b + 1 for b in self.buckets_read],
            "max_motion_px": self.max_motion_px,
            "image_motion_px_total": round(self.motion_px_total, 3),
            "coarsened": self.coarsened,
            "tick_s": str(timeline.tick_s),
            "strata": [
                {
                    "start_s": float(timeline.seconds(a)),
                    "end_s": float(timeline.seconds(b)),
                    "render_time_s": float(t),
                }
                for a, b, t in zip(self.starts_ticks, self.ends_ticks, self.times_s)
            ],
            "notes": self.notes,
        }


def _image_path_length(scene: SceneModel, times_s: np.ndarray, width: int, height: int) -> np.ndarray:
    """Cumulative image-space path length (px) of the fastest moving point at ``times_s``."""
    pts = np.asarray(scene.motion_points(times_s), dtype=np.float64)  # (T, M, 3)
    px = scene.camera.project(pts, width, height)  # (T, M, 2)
    step = np.linalg.norm(np.diff(px, axis=0), axis=-1).max(axis=1)  # (T-1,)
    return np.concatenate([[0.0], np.cumsum(step)])


def _split_interval(scene, tl: Timeline, a: int, b: int, render: RenderSection) -> tuple[list[int], float]:
    """Boundaries inside [a, b] so that each piece moves at most max_motion_px."""
    ticks = np.unique(np.linspace(a, b, _MOTION_SAMPLES + 1).round().astype(np.int64))
    s = _image_path_length(scene, tl.seconds(ticks), render.width, render.height)
    total = float(s[-1])
    n = max(1, int(np.ceil(total / render.max_motion_px - 1e-9)))
    n = min(n, len(ticks) - 1)
    targets = np.linspace(0.0, total, n + 1)[1:-1]
    inner = np.interp(targets, s, ticks.astype(np.float64)).round().astype(np.int64) if n > 1 else np.array([], np.int64)
    return [a, *inner.tolist(), b], total


def make_plan(
    timeline: Timeline,
    scene: SceneModel,
    render: RenderSection,
    rng: np.random.Generator,
) -> Plan:
    intervals = timeline.collecting_intervals()
    notes: list[str] = []
    motion_total = 0.0
    if scene.is_static:
        edges = [intervals[0][0], intervals[-1][1]]
        notes.append("static scene: one stratum")
    else:
        edges = []
        for a, b in intervals:
            cuts, moved = _split_interval(scene, timeline, a, b, render)
            motion_total += moved
            edges.extend(cuts if not edges or edges[-1] != cuts[0] else cuts[1:])
    edges = np.unique(np.asarray(edges, dtype=np.int64))

    coarsened = False
    if len(edges) - 1 > render.max_strata:
        keep = np.unique(np.linspace(0, len(edges) - 1, render.max_strata + 1).round().astype(int))
        edges = edges[keep]
        coarsened = True
        notes.append(
            f"coarsened to render.max_strata={render.max_strata} strata; image motion per stratum "
            f"now up to ~{motion_total / render.max_strata:.2f} px"
        )

    buckets_read = tuple(sorted({b for r in timeline.reads for b in r.buckets}))
    all_groups = scene.groups
    w = timeline.weights_ticks(edges, all_groups, scene.switchable)  # (J, K, G) ticks
    read_mask = np.zeros(timeline.n_buckets, dtype=bool)
    read_mask[list(buckets_read)] = True
    w[:, ~read_mask, :] = 0
    used_g = w.sum(axis=(0, 1)) > 0
    groups = tuple(g for g, u in zip(all_groups, used_g) if u)
    left_out = tuple(g for g, u in zip(all_groups, used_g) if not u)
    unknown = timeline.switchable_groups() - set(all_groups)
    if unknown:
        raise ConfigError(
            f"capture.schedule: emitter group(s) {sorted(unknown)} are not in scene {scene.name!r} "
            f"(its groups: {list(all_groups)})"
        )
    not_switchable = timeline.switchable_groups() - set(scene.switchable)
    if not_switchable:
        raise ConfigError(
            f"capture.schedule: group(s) {sorted(not_switchable)} of scene {scene.name!r} are always on and cannot be "
            f"switched (switchable: {sorted(scene.switchable)})"
        )
    w = w[:, :, used_g]
    live = w.sum(axis=(1, 2)) > 0  # strata in idle gaps (sequential frames) carry no weight
    starts, ends, w = edges[:-1][live], edges[1:][live], w[live]
    # jittered (stratified) render time inside each stratum: unbiased on average over seeds
    times = timeline.seconds(starts) + rng.random(len(starts)) * timeline.seconds(ends - starts)
    return Plan(
        starts_ticks=starts,
        ends_ticks=ends,
        times_s=np.asarray(times, dtype=np.float64),
        weights_s=w.astype(np.float64) * float(timeline.tick_s),
        groups=groups,
        buckets_read=buckets_read,
        spp=render.spp,
        max_motion_px=render.max_motion_px,
        motion_px_total=motion_total,
        coarsened=coarsened,
        left_out_groups=left_out,
        notes=notes,
    )
