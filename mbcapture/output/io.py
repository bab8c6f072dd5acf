"""Outputs: linear EXR (OpenEXR), sRGB PNG previews, JSON/YAML, all written atomically.

A run writes every file into a hidden staging folder beside the outputs and moves each one
into place with ``os.replace`` only when the whole run has succeeded. An interrupted or
failed run leaves the previous run's files in the same folder untouched and no partial file.
A run killed outright (SIGKILL) leaves its hidden ``.staging-<host>-<pid>-*`` folder behind;
the next run into the same folder removes it (:func:`remove_stale_staging`).
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import socket
import tempfile
import threading
from contextlib import contextmanager
from io import BytesIO
from pathlib import Path
from typing import Callable, Iterator, Mapping

import numpy as np
import yaml

from ..errors import MBCaptureError
from ..metrics import luminance

CHANNELS_RGB = ("R", "G", "B")


class OutputError(MBCaptureError):
    pass


def check_out_dir(out: Path) -> None:
    """Fail early (before any rendering) if ``out`` could not be created or written; leaves nothing behind.

    Permission bits are not enough (root passes ``os.access`` on ``/proc``, read-only mounts
    and full quotas say nothing), so this really creates the missing folders and a probe file in
    the deepest one, and removes what it made."""
    out = Path(out).absolute()
    probe = out
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir():
        raise OutputError(f"--out {out}: {probe} is a file, not a folder")
    missing = [out, *out.parents][: len(out.parts) - len(probe.parts)]  # deepest first
    made: list[Path] = []
    try:
        for folder in reversed(missing):
            folder.mkdir()
            made.append(folder)
        fd, name = tempfile.mkstemp(prefix=".mbcapture-probe-", dir=out)
        os.close(fd)
        os.unlink(name)
    except OSError as exc:
        created = len(made) == len(missing)  # the folder exists: writing into it failed
        at = out if created else (made[-1] if made else probe)
        if isinstance(exc, PermissionError):
            raise OutputError(f"--out {out}: {at} is not writable") from None
        raise OutputError(
            f"--out {out}: cannot {'write into' if created else 'create a folder in'} {at} ({exc.strerror})"
        ) from None
    finally:
        for folder in reversed(made):
            try:
                folder.rmdir()
            except OSError:
                pass


def prepare_out_dir(out: Path) -> Path:
    """Create ``out`` (and parents) or fail with a one-line error if it is not writable."""
    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"--out {out}: cannot create output folder ({exc.strerror})") from None
    if not os.access(out, os.W_OK | os.X_OK):
        raise OutputError(f"--out {out}: output folder is not writable")
    return out


class Staging:
    """Files written during a run; moved into the output folder by :func:`staged_outputs`."""

    def __init__(self, root: Path):
        self.root = root
        self.names: list[str] = []

    def path(self, name: str) -> Path:
        if name not in self.names:
            self.names.append(name)
        return self.root / name

    def write_bytes(self, name: str, data: bytes) -> None:
        self.path(name).write_bytes(data)

    def write_json(self, name: str, data) -> None:
        self.path(name).write_text(json.dumps(data, indent=2, sort_keys=False, default=_json_default) + "\n")

    def write_yaml(self, name: str, data) -> None:
        self.path(name).write_text(yaml.safe_dump(data, sort_keys=False))

    def write_exr(
        self,
        name: str,
        layers: Mapping[str, "np.ndarray | Callable[[], np.ndarray]"],
        channels=CHANNELS_RGB,
        empty: "Callable[..., np.ndarray]" = np.empty,
    ) -> None:
        write_exr(self.path(name), layers, channels, empty)

    def write_png(self, name: str, rgb_linear: np.ndarray, percentile: float | None = 99.5) -> None:
        write_png(self.path(name), rgb_linear, percentile)


STAGING_PREFIX = ".staging-"
"""Staging folders are ``.staging-<host>-<pid>-<random>`` inside the output folder."""


def _staging_owner(name: str) -> tuple[str, int] | None:
    """(host, pid) of a staging folder's name, or None for a name not made by this version."""
    if not name.startswith(STAGING_PREFIX):
        return None
    parts = name[len(STAGING_PREFIX) :].rsplit("-", 2)
    if len(parts) != 3 or not parts[1].isdigit():
        return None
    return parts[0], int(parts[1])


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return True


def remove_stale_staging(out: Path) -> list[str]:
    """Remove the staging folders of killed runs (SIGKILL, power loss) from ``out``: those made on
    this host by a process that no longer exists. A live run's folder, another host's, and names
    this version did not make are left alone. Returns the names removed."""
    removed = []
    host = socket.gethostname()
    for p in Path(out).glob(STAGING_PREFIX + "*"):
        owner = _staging_owner(p.name)
        if owner is None or owner[0] != host or owner[1] == os.getpid() or _process_alive(owner[1]):
            continue
        shutil.rmtree(p, ignore_errors=True)
        removed.append(p.name)
    return removed


@contextmanager
def _signals_deferred():
    """Hold SIGINT/SIGTERM/SIGHUP back while the outputs are moved into place (a few renames), so that
    Ctrl-C cannot leave half of the new files beside half of the old ones. SIGKILL cannot be held."""
    sigs = {getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, n)}
    if not hasattr(signal, "pthread_sigmask") or threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, sigs)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


@contextmanager
def staged_outputs(out: Path) -> Iterator[Staging]:
    out = prepare_out_dir(out)
    remove_stale_staging(out)
    root = Path(tempfile.mkdtemp(prefix=f"{STAGING_PREFIX}{socket.gethostname()}-{os.getpid()}-", dir=out))
    staging = Staging(root)
    try:
        yield staging
        with _signals_deferred():
            for name in staging.names:
                os.replace(root / name, out / name)
    except (OSError, RuntimeError) as exc:
        reason = _write_failure(exc)
        if reason is None:
            raise
        raise OutputError(
            f"--out {out}: writing the outputs failed ({reason}); nothing was replaced, the previous output is kept"
        ) from None
    finally:
        shutil.rmtree(root, ignore_errors=True)


#: errno values of a write that the disk, not the program, refused.
_DISK_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO, errno.EROFS}


def _write_failure(exc: BaseException) -> str | None:
    """Why a write failed, when the file system refused it (disk full, quota, read-only, I/O
    error); None for anything else (a bug is not turned into a one-line message). OpenEXR reports
    such failures as a RuntimeError naming the system's message."""
    if isinstance(exc, OSError) and exc.errno in _DISK_ERRNOS:
        return exc.strerror or str(exc)
    if isinstance(exc, RuntimeError):
        for e in _DISK_ERRNOS:
            if os.strerror(e) in str(exc):
                return os.strerror(e)
    return None


def _json_default(obj):
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.floating,)):
        return float(obj)
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serializable: {type(obj).__name__}")


# ----------------------------------------------------------------------------- EXR
def write_exr(
    path: Path,
    layers: Mapping[str, "np.ndarray | Callable[[], np.ndarray]"],
    channels=CHANNELS_RGB,
    empty: "Callable[..., np.ndarray]" = np.empty,
) -> None:
    """Write layers ``{'B1': (H, W, C) array, ...}`` as float32 channels ``B1.R, B1.G, ...``.

    A 2-D array becomes a single channel named after its layer. A layer may be given as a function
    that makes its array, called when the layer is converted and let go after it (so that arrays made
    for the file, such as exposure x k_e, are not all held at once). ``empty(shape, dtype)`` makes the
    float32 channels OpenEXR writes from, which its Python binding takes whole (np.empty, or a spilled
    film's :meth:`mbcapture.exposure.filmstore.FilmStore.empty`, so a large film's channels are not all in memory).
    """
    import OpenEXR

    chans = {}
    for layer, arr in layers.items():
        arr = np.asarray(arr() if callable(arr) else arr)
        if arr.ndim == 2:
            chans[layer] = dst = empty(arr.shape, np.float32)
            dst[...] = arr
            continue
        if arr.shape[-1] != len(channels):
            raise ValueError(f"layer {layer}: {arr.shape[-1]} channels, expected {len(channels)}")
        for ci, c in enumerate(channels):
            # a contiguous copy of each channel: non-contiguous slices are written silently wrong by OpenEXR 3.x
            chans[f"{layer}.{c}"] = dst = empty(arr.shape[:-1], np.float32)
            dst[...] = arr[..., ci]
        del arr
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, chans) as f:
        f.write(str(path))


def read_exr(path: Path, channels=CHANNELS_RGB) -> dict[str, np.ndarray]:
    """Read an EXR written by :func:`write_exr` back into ``{layer: (H, W, C)}`` (or (H, W))."""
    import OpenEXR

    with OpenEXR.File(str(path), separate_channels=True) as f:
        raw = {name: np.array(ch.pixels) for name, ch in f.channels().items()}
    layers: dict[str, dict[str, np.ndarray]] = {}
    out: dict[str, np.ndarray] = {}
    for name, px in raw.items():
        layer, _, chan = name.rpartition(".")
        if layer and chan in channels:
            layers.setdefault(layer, {})[chan] = px
        else:
            out[name] = px
    for layer, chans in layers.items():
        out[layer] = np.stack([chans[c] for c in channels if c in chans], axis=-1)
    return out


# ----------------------------------------------------------------------------- PNG
#: Samples (row x column x channel) :func:`tonemap` encodes at a time.
TONEMAP_BAND_SAMPLES = 1 << 18


def tonemap(rgb_linear: np.ndarray, percentile: float | None = 99.5) -> np.ndarray:
    """Linear RGB (H, W, 3), or grey (H, W) / (H, W, 1), -> 8-bit sRGB: scale so the luminance
    ``percentile`` maps to 1 (None: 1.0 is white), clip, and apply the sRGB transfer function
    (colour-science)."""
    import colour

    rgb = np.array(rgb_linear, dtype=np.float64)  # one copy, made finite and scaled in place
    np.nan_to_num(rgb, copy=False, nan=0.0, posinf=0.0, neginf=0.0)
    if rgb.ndim == 2:
        rgb = rgb[..., None]
    if rgb.shape[-1] == 1:
        rgb = np.repeat(rgb, 3, axis=-1)
    if percentile is None:
        white = 1.0
    else:
        white = np.percentile(luminance(rgb), percentile) if rgb.size else 1.0
    # elementwise from here, a band of rows at a time (the same values as the whole image at once): the
    # encoding's temporaries are a band's, not several copies of a large film's image
    out = np.empty(rgb.shape, np.uint8)
    rows = max(1, TONEMAP_BAND_SAMPLES // max(1, rgb[0].size)) if rgb.shape[0] else 1
    for r0 in range(0, rgb.shape[0], rows):
        band = rgb[r0 : r0 + rows]
        if white > 0:
            band /= white
            np.clip(band, 0.0, 1.0, out=band)
        else:
            band[...] = 0.0
        out[r0 : r0 + rows] = np.round(colour.cctf_encoding(band, function="sRGB") * 255)
    return out


def write_png(path: Path, rgb_linear: np.ndarray, percentile: float | None = 99.5) -> None:
    from PIL import Image

    Image.fromarray(tonemap(rgb_linear, percentile), mode="RGB").save(path, format="PNG")


# ----------------------------------------------------------------------------- videos
def tonemapped_frames(frames: np.ndarray, white: float) -> np.ndarray:
    """(F, H, W, 3) uint8 sRGB with one white level for every frame; H and W padded to even sizes (H.264)."""
    out = np.stack([tonemap(f / white, None) for f in frames])
    pad_h, pad_w = out.shape[1] % 2, out.shape[2] % 2
    if pad_h or pad_w:
        out = np.pad(out, ((0, 0), (0, pad_h), (0, pad_w), (0, 0)), mode="edge")
    return out


def encode_mp4(frames_u8: np.ndarray, fps: float) -> bytes:
    """H.264 MP4 bytes of (F, H, W, 3) uint8 frames (imageio's ffmpeg plugin; yuv420p, even sizes)."""
    import imageio.v2 as iio

    fd, tmp = tempfile.mkstemp(suffix=".mp4")
    os.close(fd)
    try:
        with iio.get_writer(
            tmp,
            format="FFMPEG",
            fps=fps,
            codec="libx264",
            quality=8,
            macro_block_size=1,
            pixelformat="yuv420p",
            ffmpeg_log_level="error",
        ) as w:
            for f in frames_u8:
                w.append_data(f)
        return Path(tmp).read_bytes()
    finally:
        os.unlink(tmp)


def encode_gif(frames_u8: np.ndarray, fps: float) -> bytes:
    """Animated GIF bytes (looping) of (F, H, W, 3) uint8 frames (imageio with Pillow)."""
    import imageio.v3 as iio

    buf = BytesIO()
    iio.imwrite(buf, frames_u8, extension=".gif", duration=1000.0 / fps, loop=0)
    return buf.getvalue()
