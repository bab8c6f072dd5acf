"""A status line for the stages of a run, so that no stage is silent.

Stages with a count of their own (render passes, figures) show a tqdm bar of it; the others
(reconstruction, writing outputs, reference renders inside an application) are single calls that
can take tens of seconds. :class:`StageStatus` shows, on one tqdm line, the stage running now,
how long it has run and how many stages are done, refreshed by a background thread every
``interval_s`` (tqdm itself only redraws when a bar is updated).
"""

from __future__ import annotations

import sys
import threading
import time
from contextlib import contextmanager
from typing import Iterator, TextIO


def _isatty(file) -> bool:
    try:
        return bool(file.isatty())
    except (AttributeError, ValueError):
        return False


class StageStatus:
    """``with status.stage("reconstruct"): ...`` shows 'reconstruct  12.5 s  [stage 5/7, 31 s]'.

    ``enabled=False`` shows nothing (and starts no thread). ``stages``: how many stages the run
    has (for the 'stage i/n' count; None leaves it out). ``interval_s``: seconds between redraws
    (default 0.5 on a terminal, 10 into a file). ``refreshes`` counts redraws (tests).
    """

    def __init__(
        self,
        enabled: bool = True,
        stages: int | None = None,
        *,
        file: TextIO | None = None,
        interval_s: float | None = None,
    ):
        file = file if file is not None else sys.stderr
        self.enabled = enabled
        self.stages = stages
        # a terminal redraws in place; a log file gets every redraw appended: fewer of them there
        self.interval_s = interval_s if interval_s is not None else (0.5 if _isatty(file) else 10.0)
        self.refreshes = 0
        self._done = 0
        self._continues = False  # the stage shown is a part of the last one counted
        self._next_continues = False
        self._name: str | None = None
        self._t_stage = self._t0 = time.perf_counter()
        self._bar = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        # a terminal gets one line redrawn in place (tqdm); a file or a pipe gets plain lines, no carriage return
        # or cursor escape: a log reads as lines
        self._file = None if _isatty(file) else file
        if enabled and self._file is None:
            from tqdm import tqdm

            self._bar = tqdm(total=stages, bar_format="{desc}", leave=False, dynamic_ncols=True, file=file)

    def _text(self) -> str:
        now = time.perf_counter()
        if not self.stages:
            count = ""
        elif self._continues:
            count = f"part of stage {self._done}/{self.stages}, "
        else:
            count = f"stage {self._done + 1}/{self.stages}, "
        return f"{self._name}  {now - self._t_stage:.1f} s  [{count}{now - self._t0:.0f} s in all]"

    def refresh(self) -> None:
        if self._name is None or not self.enabled:
            return
        if self._bar is not None:
            self._bar.set_description_str(self._text(), refresh=True)
        else:
            self._file.write(self._text() + "\n")
            self._file.flush()
        self.refreshes += 1

    def _tick(self) -> None:
        while not self._stop.wait(self.interval_s):
            self.refresh()

    def continued(self) -> None:
        """The next stage is a part of the last one counted: one that only some runs need (a top-up render,
        adaptive sampling's refinement), so the count and its total, fixed at the start, stay as they are."""
        self._next_continues = True

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        """Show ``name`` (and its running time) while the block runs."""
        continues, self._next_continues = self._next_continues, False
        if not self.enabled:
            yield
            return
        self._name, self._t_stage, self._continues = name, time.perf_counter(), continues
        self.refresh()
        if self._thread is None:
            self._thread = threading.Thread(target=self._tick, name="mbcapture-status", daemon=True)
            self._thread.start()
        try:
            yield
        finally:
            self._done += not continues

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        if self._bar is not None:
            self._bar.close()

    def __enter__(self) -> "StageStatus":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class _Lines:
    """A file that takes tqdm's redraws as plain lines: carriage returns and cursor escapes dropped, a blank
    redraw (tqdm clearing its line) skipped, each redraw its own line."""

    def __init__(self, file: TextIO):
        self._file = file

    def write(self, text: str) -> None:
        text = text.replace("\r", "").replace("\x1b[A", "")
        if text.strip():
            self._file.write(text.rstrip("\n") + "\n")

    def flush(self) -> None:
        self._file.flush()


def bar(iterable=None, *, total: int | None = None, desc: str, unit: str, enabled: bool = True, **kw):
    """A tqdm progress bar on stderr: redrawn in place on a terminal; into a file or a pipe, a plain line every
    10 s (no carriage return or cursor escape: a log reads as lines)."""
    from tqdm import tqdm

    tty = _isatty(sys.stderr)
    return tqdm(
        iterable,
        total=total,
        desc=desc,
        unit=unit,
        disable=not enabled,
        leave=False,
        dynamic_ncols=tty,
        file=sys.stderr if tty else _Lines(sys.stderr),
        mininterval=0.1 if tty else 10.0,
        **kw,
    )
