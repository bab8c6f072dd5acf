"""The base of every config section: :class:`StrictModel`, a pydantic model that refuses a key it does not
know (``extra="forbid"``, so a misspelt key is an error that names it) and cannot be changed once made
(``frozen``: a config is hashable, and what a run was given stays what it was given)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict


class StrictModel(BaseModel):
    """A config section: unknown keys refused, frozen once validated."""

    model_config = ConfigDict(extra="forbid", frozen=True)
