"""mbcapture: a physically based capture pipeline for multi-bucket image sensors, on Mitsuba 3.

Public API::

    cfg = load_config("configs/metronome_hdr.yaml", ["render.spp=4"])
    result = run_capture(cfg, "out/metronome")

Mitsuba is imported only when a capture renders (inside :mod:`mbcapture.render`).
"""

from . import capture
from .config import load_config
from .errors import ConfigError, EnvironmentProblem, MBCaptureError

__all__ = ["load_config", "run_capture", "CaptureResult", "ConfigError", "EnvironmentProblem", "MBCaptureError"]
__version__ = "0.1.0"


def __getattr__(name):  # lazy: `import mbcapture` stays light
    if name == "load_config":
        return load_config
    if name in ("run_capture", "CaptureResult"):
        return getattr(capture, name)
    raise AttributeError(name)
