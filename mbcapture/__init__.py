"""mbcapture: a physically based capture pipeline for multi-bucket image sensors, on Mitsuba 3.

Public API::

    cfg = load_config("configs/metronome_hdr.yaml", ["render.spp=4"])
    result = run_capture(cfg, "out/metronome")

Mitsuba is imported only when a capture renders (inside :mod:`mbcapture.render`).
"""

from .capture.pipeline import CaptureResult
from .capture.run import run_capture
from .config import load_config
from .errors import ConfigError, EnvironmentProblem, MBCaptureError

__all__ = ["load_config", "run_capture", "CaptureResult", "ConfigError", "EnvironmentProblem", "MBCaptureError"]
__version__ = "0.1.0"
