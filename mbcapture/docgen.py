"""Generate ``docs/config.md`` from the config models, so the documentation of every key is the
code's own ``Field(description=...)``. A test fails when the file is out of date.

    python -m mbcapture.docgen > docs/config.md
"""

from __future__ import annotations

import inspect
import json

from pydantic import BaseModel

from . import application as apps
from .scene import scenes
from .config import AppSection, CaptureConfig, ReadSpec, ScheduleSpec, SlotSpec
from .sweep.spec import Axes, RandomAxes, RandomKey, SweepSpec


def _default(field) -> str:
    if field.is_required():
        return "(required)"
    value = field.get_default(call_default_factory=True)
    if isinstance(value, BaseModel):
        return "(section)"
    return f"`{json.dumps(value)}`" if value is not None else "`null`"


def _table(model: type[BaseModel], prefix: str) -> list[str]:
    rows = ["| key | default | meaning |", "| --- | --- | --- |"]
    for name, field in model.model_fields.items():
        desc = (field.description or "").replace("|", "\\|").replace("\n", " ")
        rows.append(f"| `{prefix}{name}` | {_default(field)} | {desc} |")
    return rows


def config_markdown() -> str:
    out = [
        "# Configuration keys",
        "",
        "Generated from the code by `python -m mbcapture.docgen > docs/config.md`; do not edit by hand.",
        "Any key can be overridden on the command line: `--set section.key=VALUE` (VALUE is YAML).",
        "Unknown keys are errors. Units are in the names (`_s` seconds, `_e` electrons, `_px` pixels).",
        "",
        "## Top level",
        "",
        *_table(CaptureConfig, ""),
    ]
    for section, field in CaptureConfig.model_fields.items():
        ann = field.annotation
        if isinstance(ann, type) and issubclass(ann, BaseModel) and section not in ("scene", "app"):
            out += ["", f"## `{section}`", ""]
            if ann.__doc__ and not ann.__doc__.startswith("Usage docs"):
                out += [ann.__doc__.strip(), ""]
            out += _table(ann, f"{section}.")
    out += ["", "## `capture.schedule` (protocol `custom`)", "", *_table(ScheduleSpec, "capture.schedule.")]

    out += ["", "Each slot:", "", *_table(SlotSpec, "slots[]."), "", "Each read:", "", *_table(ReadSpec, "reads[].")]
    out += ["", "## `scene`", "", "`scene.name` picks the scene; the other `scene.*` keys are the scene's own:"]
    for name in scenes.available():
        mod = scenes.load_module(name)
        out += ["", f"### scene `{name}`", "", mod.DESCRIPTION, "", *_table(mod.Params, "scene.")]

    out += ["", "## `app`", "", inspect.cleandoc(AppSection.__doc__), "", *_table(AppSection, "app.")]
    for name in apps.names():
        app = apps.get(name)
        used_by = [p for p in apps.protocol_names() if apps.protocol_app(p) == name]
        out += ["", f"### app `{name}`", "", app.description, ""]
        if used_by:
            out += [f"Default for protocol(s): {', '.join(f'`{p}`' for p in used_by)}.", ""]
        else:
            out += [f"Chosen with `app.name: {name}` over any protocol.", ""]
        keys = {k: f for k, f in app.params.model_fields.items()}
        out += [*_table(app.params, "app."), ""] if keys else ["No parameters of its own.", ""]
        out.pop()
    out += _sweep_section()
    return "\n".join(out) + "\n"


def _sweep_section() -> list[str]:
    """The keys of a sweep file (``mbcapture sweep``)."""

    return [
        "",
        "## Sweep files (`mbcapture sweep`)",
        "",
        "A sweep file names a base config and the keys that vary; configs/sweeps/ has commented examples.",
        "",
        *_table(SweepSpec, ""),
        "",
        "`axes`:",
        "",
        *_table(Axes, "axes."),
        "",
        "`axes.random`:",
        "",
        *_table(RandomAxes, "axes.random."),
        "",
        "Each key of `axes.random.keys`:",
        "",
        *_table(RandomKey, "axes.random.keys.<key>."),
    ]


if __name__ == "__main__":
    print(config_markdown(), end="")
