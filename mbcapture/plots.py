"""Drawing shared by the paper's figures (:mod:`mbcapture.figures`) and every run's report.html
(:mod:`mbcapture.report`): a gate schedule as coloured slots on a time axis. matplotlib is
imported where a drawing needs it, so importing this module costs nothing.
"""

from __future__ import annotations

#: One colour per bucket (bucket k: ``BUCKET_COLOURS[k % 6]``), in figures and reports alike.
BUCKET_COLOURS = ["#d62728", "#1f77b4", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b"]


def draw_timeline(ax, tl, y: float, unit_s: float, label: str, height: float = 0.6, *, colour=None,
                  until_tick: int | None = None, background: str = "#dddddd") -> int:
    """Coloured slots on a horizontal bar at ``y`` over a ``background`` bar (idle time), x in units of
    ``unit_s`` from the capture's start. ``colour(slot)``: the slot's colour or None to leave it out
    (default: one colour per bucket, drained slots left out). ``until_tick``: draw only the slots
    that start before it (a long schedule's first periods). Returns the number of slots drawn.
    The paper's timing figures and every run's report.html draw their schedules with it."""
    colour = colour or (lambda s: BUCKET_COLOURS[s.bucket % len(BUCKET_COLOURS)] if s.bucket >= 0 else None)
    t0 = tl.start_tick
    stop = tl.end_tick if until_tick is None else min(until_tick, tl.end_tick)
    drawn = 0
    for seg in tl.segments:
        tick = seg.start_tick
        for _ in range(seg.repeats):
            if tick >= stop:
                break
            for s in seg.slots:
                c = colour(s) if tick < stop else None
                if c is not None:
                    x = float((tick - t0) * tl.tick_s) / unit_s
                    w = float(s.ticks * tl.tick_s) / unit_s
                    ax.add_patch(_rect(x, y - height / 2, w, height, c))
                    drawn += 1
                tick += s.ticks
    end = float((stop - t0) * tl.tick_s) / unit_s
    ax.add_patch(_rect(0, y - height / 2, end, height, background, zorder=0))
    if label:
        ax.text(-0.02 * end, y, label, ha="right", va="center", fontsize=9)
    return drawn


def _rect(x, y, w, h, colour, zorder=1):
    from matplotlib.patches import Rectangle

    return Rectangle((x, y), w, h, facecolor=colour, edgecolor="none", zorder=zorder)
