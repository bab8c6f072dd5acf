"""When the gates open: integer-tick timelines, the named gate schedules, per-pixel gate codes, emitter drives."""
