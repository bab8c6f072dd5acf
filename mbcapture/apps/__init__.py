"""Applications: what a capture's reads are turned into (HDR, flash/no-flash, colour, ...).

Each module here is one application: its protocol, its reconstruction (the algorithms themselves
live in :mod:`mbcapture.reconstruct`), its ground truth and its metrics. It registers itself with
:func:`mbcapture.application.register`, where the registry and the data contract
(:class:`CaptureData` in, :class:`AppOutput` out) live, low in the house; this package re-exports
those names for its modules. Protocols name the application that reads them by default
(:func:`mbcapture.application.register_protocol`); ``app.name`` overrides it, e.g. to reconstruct a
``custom`` schedule with the flash/no-flash method.
"""

from ..application import App, AppOutput, CaptureData, NoParams, get, load_all, names, register, register_protocol

__all__ = ["App", "AppOutput", "CaptureData", "NoParams", "get", "load_all", "names", "register", "register_protocol"]
