"""sRGB PNG output for looking at images (docs/ARCHITECTURE.md, Conventions: EXR for data, sRGB PNG only for looking).

The encoder is a small dependency-free PNG writer (zlib + struct): 8-bit greyscale, RGB or RGBA,
no interlacing, filter type 0 on every row. Files are written atomically (temporary sibling file,
then ``os.replace``), so a reader never sees a half-written PNG.

>>> import numpy as np
>>> png = encode_png(np.zeros((2, 3, 3), np.uint8))
>>> png[:8] == b"\\x89PNG\\r\\n\\x1a\\n"
True
"""

from __future__ import annotations

import os
import struct
import tempfile
import zlib
from pathlib import Path

import numpy as np

from ..errors import InputError

__all__ = ["srgb_oetf", "to_srgb8", "encode_png", "write_png", "NO_DATA"]

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: the colour of "no data" (no surface, no cascade, no tile: −1 or NaN) in every preview image
NO_DATA = np.array([128, 128, 128], np.uint8)
_COLOR_TYPE = {1: 0, 3: 2, 4: 6}  # channels -> PNG colour type (grey, RGB, RGBA)


def srgb_oetf(x: np.ndarray) -> np.ndarray:
    """The sRGB transfer function (IEC 61966-2-1), linear [0, 1] -> encoded [0, 1]; input is clipped.

    >>> [round(float(v), 4) for v in srgb_oetf(np.array([0.0, 0.5, 1.0]))]
    [0.0, 0.7354, 1.0]
    """
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


def to_srgb8(img_linear, exposure: float = 1.0) -> np.ndarray:
    """Linear float image (H×W, H×W×1 or H×W×3) times ``exposure`` -> sRGB uint8 H×W×3 (clipped).

    Greyscale input is replicated to three channels. Non-finite values raise ``InputError``
    (a NaN would otherwise turn silently into black).

    >>> to_srgb8(np.array([[0.0, 0.5, 1.0, 4.0]])).tolist()[0]
    [[0, 0, 0], [188, 188, 188], [255, 255, 255], [255, 255, 255]]
    """
    a = np.asarray(img_linear, dtype=np.float64)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    if a.ndim == 2:
        a = np.repeat(a[:, :, None], 3, axis=2)
    if a.ndim != 3 or a.shape[2] != 3:
        raise InputError(
            f"to_srgb8: expected an H×W or H×W×3 image, got shape {a.shape}; "
            "drop the alpha channel or pick three channels first"
        )
    if not np.all(np.isfinite(a)):
        raise InputError("to_srgb8: the image contains NaN or inf values; fix the renderer output first")
    exposure = float(exposure)
    if not np.isfinite(exposure) or exposure < 0:
        raise InputError(f"to_srgb8: exposure must be a finite number >= 0, got {exposure}")
    return np.round(srgb_oetf(a * exposure) * 255.0).astype(np.uint8)


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def encode_png(img_uint8: np.ndarray, compress_level: int = 6) -> bytes:
    """PNG file bytes of a uint8 image: H×W (grey), H×W×1, H×W×3 (RGB) or H×W×4 (RGBA).

    >>> b = encode_png(np.full((4, 5), 7, np.uint8))
    >>> int.from_bytes(b[16:20], "big"), int.from_bytes(b[20:24], "big")  # IHDR width, height
    (5, 4)
    """
    a = np.asarray(img_uint8)
    if a.dtype != np.uint8:
        raise InputError(f"encode_png: expected a uint8 array, got {a.dtype}; use to_srgb8() for float images")
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3 or a.shape[2] not in _COLOR_TYPE or a.shape[0] < 1 or a.shape[1] < 1:
        raise InputError(f"encode_png: expected H×W, H×W×1, H×W×3 or H×W×4 with H, W >= 1, got shape {a.shape}")
    h, w, c = a.shape
    # One filter byte (0 = none) in front of every row.
    raw = np.empty((h, 1 + w * c), np.uint8)
    raw[:, 0] = 0
    raw[:, 1:] = np.ascontiguousarray(a).reshape(h, w * c)
    ihdr = struct.pack(">IIBBBBB", w, h, 8, _COLOR_TYPE[c], 0, 0, 0)
    return (
        PNG_SIGNATURE
        + _chunk(b"IHDR", ihdr)
        + _chunk(b"IDAT", zlib.compress(raw.tobytes(), compress_level))
        + _chunk(b"IEND", b"")
    )


def write_bytes_atomic(path, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temporary sibling file and ``os.replace`` (atomic)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    return path


def write_png(path, img, exposure: float = 1.0) -> Path:
    """Write a PNG atomically. uint8 images are written as they are; float images are taken as
    linear and go through ``to_srgb8(img, exposure)``. Returns the path.

    >>> import tempfile, os
    >>> p = write_png(os.path.join(tempfile.mkdtemp(), "a.png"), np.ones((8, 8, 3)) * 0.5)
    >>> p.read_bytes()[:4]
    b'\\x89PNG'
    """
    a = np.asarray(img)
    if a.dtype != np.uint8:
        if not (np.issubdtype(a.dtype, np.floating) or a.dtype == bool):
            raise InputError(
                f"write_png({path}): unsupported dtype {a.dtype}; pass uint8 (sRGB) or float (linear)"
            )
        a = to_srgb8(a, exposure)
    return write_bytes_atomic(path, encode_png(a))
