"""Multi-bucket sensor model, pure numpy, ordered as the physics.

:mod:`.config` the parameters, :mod:`.photons` radiance to expected electrons, :mod:`.cfa` the
colour filter array and demosaicing,
:mod:`.readout` shot noise, full wells, floating-diffusion sums, read noise and ADC.
"""

from .config import SensorConfig
from .photons import (
    electrons_per_film_second,
    electrons_per_radiance_second,
    electrons_per_render_second,
    expected_electrons,
    mono_weights,
)
from .readout import (
    FixedPattern,
    SensorReads,
    develop_reads,
    dn_to_electrons,
    fixed_pattern,
    join_rows,
    sensor_stage_hook,
    simulate_reads,
)

__all__ = [
    "FixedPattern",
    "SensorConfig",
    "SensorReads",
    "develop_reads",
    "dn_to_electrons",
    "electrons_per_film_second",
    "electrons_per_radiance_second",
    "electrons_per_render_second",
    "expected_electrons",
    "fixed_pattern",
    "join_rows",
    "mono_weights",
    "sensor_stage_hook",
    "simulate_reads",
]
