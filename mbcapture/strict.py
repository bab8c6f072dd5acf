"""The base of every config section: :class:`StrictModel`, a pydantic model that refuses a key it does not
know (``extra="forbid"``, so a misspelt key is an error that names it) and validates every value it is
given, in the YAML, by ``--set`` and by assignment through the Python API alike
(``cfg.sensor.read_noise_e = -5`` raises the :class:`~mbcapture.errors.ConfigError` that ``--set
sensor.read_noise_e=-5`` does, and leaves the old value in place).

An assignment checks its own key (its type and range, and its section's own rules); rules that join
two sections (a spectral response needs a spectral variant, exposure ratios need as many buckets)
are checked again when a run starts (:func:`mbcapture.run_capture` validates the whole config).

Also here: :func:`format_validation`, the one-line error every config error is written in."""

from __future__ import annotations

import difflib
from typing import Any, Callable

from pydantic import BaseModel, ConfigDict, PrivateAttr, ValidationError

from .errors import ConfigError


def model_at(model: type[BaseModel], path: tuple) -> type[BaseModel] | None:
    """The pydantic model of the section at ``path`` (field names) below ``model``, or None."""
    for name in path:
        field = model.model_fields.get(name) if isinstance(name, str) else None
        if field is None:
            return None
        nested = [
            a
            for a in (field.annotation, *getattr(field.annotation, "__args__", ()))
            if isinstance(a, type) and issubclass(a, BaseModel)
        ]
        if not nested:
            return None
        model = nested[0]
    return model


def suggest(key: str, section: tuple, model: type[BaseModel] | None, root: type[BaseModel] | None = None) -> str:
    """'; did you mean render.spp?': the nearest valid key of the same section (difflib), or a
    key of that name in another section of ``root`` (the whole config)."""
    valid = list(model.model_fields) if model is not None else []
    close = difflib.get_close_matches(key, valid, n=1, cutoff=0.6)
    if close:
        return f"; did you mean {'.'.join((*map(str, section), close[0]))}?"
    if root is None:
        return ""
    elsewhere = [
        f"{name}.{key}"
        for name in root.model_fields
        if (sub := model_at(root, (name,))) is not None and key in sub.model_fields
    ]
    return f"; did you mean {elsewhere[0]}?" if elsewhere else ""


def format_validation(
    exc: ValidationError,
    prefix: str = "",
    origin: Callable[[tuple], str] | None = None,
    model: type[BaseModel] | None = None,
    owner: str | None = None,
    root: type[BaseModel] | None = None,
) -> str:
    """One line for all of ``exc``'s errors: ``[origin: ]key: message`` joined by '; '.

    ``model``: the model that was validated (for the valid keys of an unknown key's section; default
    ``root``); ``root``: the whole config, where a key unknown in its section is looked for in the
    others; ``owner``: 'scene 'metronome'' when ``model`` is a scene's or application's own
    parameters, named in the message with its keys; ``origin(path)``: where the key at ``path`` came
    from (the file or a ``--set``)."""
    parts = []
    for err in exc.errors():
        path = tuple(p for p in err["loc"] if not (isinstance(p, str) and p.startswith("function-")))
        full = ((prefix,) if prefix else ()) + path
        loc = ".".join(map(str, full))
        msg = err["msg"].removeprefix("Value error, ")
        if err["type"] == "extra_forbidden":
            section = model_at(model or root, path[:-1]) if (model or root) is not None else None
            if owner and section is not None and len(path) == 1:
                msg = f"unknown key for {owner} (its keys: {', '.join(section.model_fields) or 'none'})" + suggest(
                    str(path[-1]), full[:-1], section, root
                )
            else:
                msg = "unknown key" + suggest(str(path[-1]), full[:-1], section, root)
        elif "input" in err and not isinstance(err["input"], (dict, list)):
            msg = f"{msg} (got {err['input']!r})"
        where = origin(full) if origin else ""
        parts.append(f"{where + ': ' if where else ''}{loc + ': ' if loc else ''}{msg}")
    return "; ".join(parts)


class StrictModel(BaseModel):
    """A config section: unknown keys refused, every value validated, on construction and on assignment."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    #: the section's dotted key in the whole config ('sensor', 'capture.gate_code'), named in errors;
    #: set by the config that holds it (:meth:`name_sections`)
    _key: str = PrivateAttr("")

    def name_sections(self, key: str = "") -> None:
        """Tell this section and every section below it its dotted key."""
        self._key = key
        for name in type(self).model_fields:
            value = getattr(self, name)
            if isinstance(value, StrictModel):
                value.name_sections(f"{key}.{name}" if key else name)

    def __setattr__(self, name: str, value: Any) -> None:
        if name.startswith("_"):
            super().__setattr__(name, value)
            return
        key = f"{self._key}.{name}" if self._key else name
        if name not in type(self).model_fields and type(self).model_config.get("extra") != "allow":
            raise ConfigError(f"{key}: unknown key" + suggest(name, tuple(key.split("."))[:-1], type(self)))
        try:
            super().__setattr__(name, value)
        except ValidationError as exc:
            raise ConfigError(format_validation(exc, prefix=self._key, model=type(self))) from None
        if isinstance(stored := getattr(self, name, None), StrictModel):  # a section given as a model or a mapping
            stored.name_sections(key)
