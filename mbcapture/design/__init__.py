"""``mbcapture design``: find the schedule and sensor settings that minimise an application's error
(docs/design.md): a spec (:mod:`.spec`), the search on cached renders (:mod:`.search`), its outputs
(:mod:`.results`)."""
