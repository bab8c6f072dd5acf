"""Exceptions a user can act on. The CLI prints them as one line and exits with status 2."""


class MBCaptureError(Exception):
    """Base class of errors caused by input (config, files, environment), not by a bug."""


class ConfigError(MBCaptureError):
    """A config key, value or file is wrong; the message names it and what was expected."""


class EnvironmentProblem(MBCaptureError):
    """The machine lacks something (e.g. a usable libLLVM); the message names the fix."""


class ResourceProblem(MBCaptureError):
    """A run does not fit the machine (memory, disk); the message says what it needs, what is free
    and what to change. Raised before any work."""


class ConfigNotice(UserWarning):
    """Not an error: the config was changed in a way the user should know of (e.g. ``--set
    scene.name=...`` dropped the old scene's keys). The CLI prints it as ``mbcapture: note: ...``."""


def one_line(exc: BaseException) -> str:
    """An exception as one line: the message of an input error, else 'Type: message'."""

    text = " ".join(str(exc).split())
    return text if isinstance(exc, MBCaptureError) else f"{type(exc).__name__}: {text}"
