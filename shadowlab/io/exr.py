"""EXR data images: named float32 channels, written atomically with the OpenEXR python module.

Channel names are free strings such as ``"V.key"``, ``"V.key.se"`` or ``"shaded.R"``; they are stored
and read back exactly, one H×W float32 array per channel (never merged into an RGB array). Files are
single-part scanline images, ZIP compression, FLOAT pixels, so a round trip is bit exact.

>>> import numpy as np, tempfile, os
>>> d = tempfile.mkdtemp()
>>> write_exr(os.path.join(d, "a.exr"), {"V.key": np.full((2, 3), 0.25)})
>>> read_exr(os.path.join(d, "a.exr"))["V.key"].tolist()
[[0.25, 0.25, 0.25], [0.25, 0.25, 0.25]]

Note: OpenEXR detects a truncated or garbled file, but damage inside a compressed pixel block can
decode silently into wrong values; EXR has no checksum. Keep hashes in meta.json if that matters.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Mapping
from pathlib import Path

import numpy as np
import OpenEXR

from ..errors import InputError
from .outdir import write_error

__all__ = ["write_exr", "read_exr", "rgb_channels", "stack_rgb", "split_rgb", "check_finite"]

_RGB = ("R", "G", "B")


def _openexr():
    return OpenEXR


def _coerce_channels(channels: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    if not isinstance(channels, Mapping) or len(channels) == 0:
        raise InputError(
            "write_exr needs a non-empty dict {channel name: H×W array}; got "
            f"{type(channels).__name__} {'(empty)' if isinstance(channels, Mapping) else ''}. "
            "Pass at least one channel, e.g. {'V.key': vis}."
        )
    out: dict[str, np.ndarray] = {}
    shape = None
    for name, value in channels.items():
        if not isinstance(name, str) or not name:
            raise InputError(
                f"EXR channel name {name!r} is not a non-empty string; name channels like 'V.key' "
                "or 'shaded.R'."
            )
        arr = np.asarray(value)
        if arr.ndim != 2 or arr.size == 0:
            raise InputError(
                f"EXR channel {name!r} has shape {arr.shape}; each channel must be a non-empty H×W "
                "array. Split colour images with split_rgb(img, prefix) first."
            )
        if shape is None:
            shape = arr.shape
        elif arr.shape != shape:
            raise InputError(
                f"EXR channel {name!r} has shape {arr.shape} but earlier channels are {shape}; all "
                "channels of one file must have the same H×W. Resample or write separate files."
            )
        try:
            out[name] = np.ascontiguousarray(arr, dtype=np.float32)
        except (TypeError, ValueError) as exc:
            raise InputError(
                f"EXR channel {name!r} (dtype {arr.dtype}) cannot be converted to float32: {exc}. "
                "Pass numeric arrays."
            ) from exc
    return out


def _fsync(path: str) -> None:
    with open(path, "rb") as fh:
        os.fsync(fh.fileno())


def _publish(tmp: str, path: Path, overwrite: bool) -> None:
    """Move a finished temporary file to ``path`` atomically (no clobber when ``overwrite`` is False)."""
    if overwrite:
        os.replace(tmp, path)
        return
    try:
        os.link(tmp, path)  # atomic and fails if the target exists
    except FileExistsError:
        raise _exists_error(path) from None
    except OSError:  # file system without hard links: check, then rename
        if path.exists():
            raise _exists_error(path) from None
        os.replace(tmp, path)
    else:
        os.unlink(tmp)


def _exists_error(path: Path) -> InputError:
    return InputError(
        f"{path} already exists and overwrite=False; pass overwrite=True (CLI: --force) to replace "
        "it, or choose another output path."
    )


def write_exr(path, channels: Mapping[str, np.ndarray], *, overwrite: bool = True) -> None:
    """Write named H×W channels to a single-part EXR file (ZIP, FLOAT), atomically.

    Every value is coerced to C-contiguous float32; all channels must share one H×W shape. The data
    goes to a temporary file in the target directory (created if missing), which then replaces
    ``path`` with ``os.replace``, so readers see the old file or the new one, never half of one.
    With ``overwrite=False`` an existing ``path`` raises :class:`InputError` and is left untouched.
    Non-finite values are stored as they are (use :func:`check_finite` to refuse them).

    >>> import numpy as np, tempfile, os
    >>> p = os.path.join(tempfile.mkdtemp(), "v.exr")
    >>> write_exr(p, {"V.key": np.zeros((4, 4)), "V.key.se": np.ones((4, 4))})
    >>> sorted(read_exr(p))
    ['V.key', 'V.key.se']
    """
    data = _coerce_channels(channels)
    path = Path(path)
    if not overwrite and path.exists():
        raise _exists_error(path)
    OpenEXR = _openexr()
    directory = path.parent if str(path.parent) else Path(".")
    try:
        directory.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=directory)
        os.close(fd)
    except OSError as exc:
        raise (write_error(path, exc, what="create") or exc) from None
    try:
        header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
        # OpenEXR.File replaces the dict's values by Channel objects: give it its own dict.
        with OpenEXR.File(header, dict(data)) as exr:
            exr.write(tmp)
        _fsync(tmp)
        _publish(tmp, path, overwrite)
    except (OSError, RuntimeError) as exc:  # OpenEXR reports a full disk as a RuntimeError with its text
        err = write_error(path, exc)
        if err is None:
            raise
        raise err from None
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def read_exr(path) -> dict[str, np.ndarray]:
    """Read every channel of an EXR file (first part) as ``{name: H×W float32}``, names as stored.

    Channels are returned separately (``"shaded.R"`` stays ``"shaded.R"``, never merged into RGB);
    HALF and UINT channels are converted to float32. A missing file, a file that is not an EXR, a
    truncated or corrupt file, or sub-sampled channels raise :class:`InputError` naming the file.

    >>> import numpy as np, tempfile, os
    >>> p = os.path.join(tempfile.mkdtemp(), "s.exr")
    >>> write_exr(p, split_rgb(np.ones((2, 2, 3)), "shaded"))
    >>> list(read_exr(p))
    ['shaded.B', 'shaded.G', 'shaded.R']
    """
    path = Path(path)
    if not path.exists():
        raise InputError(
            f"EXR file {path} does not exist; check the path (render or fetch the reference first)."
        )
    if not path.is_file():
        raise InputError(f"{path} is not a file; pass the path of an .exr image.")
    OpenEXR = _openexr()
    try:
        is_exr = OpenEXR.isOpenExrFile(str(path))
    except Exception:  # noqa: BLE001 - the binding raises various types on unreadable files
        is_exr = False
    if not is_exr:
        raise InputError(
            f"{path} is not an OpenEXR file (bad magic number); pass an .exr image written by "
            "shadowlab or Mitsuba, or re-render it."
        )
    try:
        with OpenEXR.File(str(path), separate_channels=True) as exr:
            if len(exr.parts) == 0:
                raise ValueError("no readable image part")
            header = exr.header()
            if header.get("type") not in (None, OpenEXR.scanlineimage, OpenEXR.tiledimage):
                raise InputError(
                    f"{path} is a deep EXR image; shadowlab reads flat scanline or tiled images. "
                    "Flatten it in the renderer."
                )
            out: dict[str, np.ndarray] = {}
            for name, chan in exr.channels().items():
                if chan.xSampling != 1 or chan.ySampling != 1:
                    raise InputError(
                        f"{path}: channel {name!r} is sub-sampled ({chan.xSampling}×{chan.ySampling});"
                        " write full-resolution channels."
                    )
                out[name] = np.ascontiguousarray(chan.pixels, dtype=np.float32)
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - RuntimeError/ValueError from the C++ library
        raise InputError(
            f"EXR file {path} is corrupt or truncated ({exc}); delete it and write it again "
            "(e.g. re-render the reference)."
        ) from exc
    if not out:
        raise InputError(f"EXR file {path} has no channels; re-render it.")
    return out


def rgb_channels(prefix: str) -> list[str]:
    """Channel names of an RGB image stored under ``prefix``.

    >>> rgb_channels("shaded")
    ['shaded.R', 'shaded.G', 'shaded.B']
    """
    return [f"{prefix}.{c}" for c in _RGB]


def stack_rgb(channels: Mapping[str, np.ndarray], prefix: str) -> np.ndarray:
    """Gather ``prefix.R/G/B`` from a channel dict into one H×W×3 float32 image.

    >>> import numpy as np
    >>> ch = {"s.R": np.zeros((1, 2)), "s.G": np.ones((1, 2)), "s.B": np.ones((1, 2))}
    >>> stack_rgb(ch, "s")[0, 0].tolist()
    [0.0, 1.0, 1.0]
    """
    names = rgb_channels(prefix)
    missing = [n for n in names if n not in channels]
    if missing:
        raise InputError(
            f"RGB image {prefix!r} is missing channel(s) {missing}; available channels: "
            f"{sorted(channels)}. Check the prefix or write the image with split_rgb()."
        )
    planes = [np.asarray(channels[n], dtype=np.float32) for n in names]
    if any(p.ndim != 2 or p.shape != planes[0].shape for p in planes):
        raise InputError(
            f"channels {names} must be H×W arrays of one shape; got {[p.shape for p in planes]}."
        )
    return np.stack(planes, axis=-1)


def split_rgb(img: np.ndarray, prefix: str) -> dict[str, np.ndarray]:
    """Split an H×W×3 image into ``{prefix.R, prefix.G, prefix.B}`` float32 channels.

    >>> import numpy as np
    >>> sorted(split_rgb(np.zeros((2, 2, 3)), "shaded"))
    ['shaded.B', 'shaded.G', 'shaded.R']
    """
    arr = np.asarray(img)
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise InputError(
            f"split_rgb({prefix!r}) needs an H×W×3 image, got shape {arr.shape}; store single "
            "channels directly under their own name."
        )
    return {n: np.ascontiguousarray(arr[..., i], dtype=np.float32)
            for i, n in enumerate(rgb_channels(prefix))}


def check_finite(name: str, array: np.ndarray, mask: np.ndarray | None = None) -> None:
    """Raise :class:`InputError` if ``array`` holds NaN or ±Inf (only pixels where ``mask`` is True).

    ``array`` is H×W or H×W×C; the message gives the count of bad values and the first bad pixel as
    (x, y) in row-major order, and how to fix it.

    >>> import numpy as np
    >>> check_finite("vis", np.zeros((2, 2)))  # returns None when all values are finite
    >>> a = np.zeros((2, 2)); a[1, 0] = np.nan
    >>> try:
    ...     check_finite("vis", a)
    ... except InputError as e:
    ...     print(str(e).split(";")[0])
    vis has 1 non-finite value (NaN/Inf), first at pixel (x=0, y=1)
    """
    arr = np.asarray(array)
    if arr.dtype.kind not in "fc":
        return
    bad = ~np.isfinite(arr)
    if mask is not None:
        m = np.asarray(mask, dtype=bool)
        bad = bad & (m if bad.ndim == m.ndim else m.reshape(m.shape + (1,) * (bad.ndim - m.ndim)))
    count = int(np.count_nonzero(bad))
    if count == 0:
        return
    if bad.ndim >= 2:
        pix = bad.reshape(bad.shape[0], bad.shape[1], -1).any(axis=2)
        y, x = np.argwhere(pix)[0]
        where = f"first at pixel (x={int(x)}, y={int(y)})"
    else:
        where = f"first at index {int(np.argwhere(bad)[0][0])}"
    raise InputError(
        f"{name} has {count} non-finite value{'s' if count != 1 else ''} (NaN/Inf), {where}; "
        "clamp or remove non-finite values in the renderer output (e.g. np.nan_to_num), or exclude "
        "those pixels with the valid mask."
    )
