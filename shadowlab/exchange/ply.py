"""Binary little-endian PLY triangle meshes: what :mod:`shadowlab.exchange.export` writes.

Layout (the one every PLY reader, Mitsuba's included, understands)::

    ply
    format binary_little_endian 1.0
    comment <free text>
    element vertex N
    property float x / y / z        world position (metres)
    property float nx / ny / nz     unit shading normal
    property float u / v            texture coordinates (Mitsuba's uv of the primitive)
    element face M
    property list uchar int vertex_indices
    end_header

Faces are triangles, counter-clockwise seen from the side their normal points to, i.e.
``cross(v1 − v0, v2 − v0)`` is the outward / front geometric normal.

>>> import numpy as np, tempfile, os
>>> p = os.path.join(tempfile.mkdtemp(), "t.ply")
>>> write_ply(p, np.eye(3), np.tile([0., 0., 1.], (3, 1)), np.zeros((3, 2)), np.array([[0, 1, 2]]))
>>> m = read_ply(p); m["positions"].shape, m["faces"].tolist()
((3, 3), [[0, 1, 2]])
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from ..errors import InputError

__all__ = ["write_ply", "read_ply"]

_VERTEX = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4"),
                    ("u", "<f4"), ("v", "<f4")])
_FACE = np.dtype([("n", "u1"), ("i", "<i4", (3,))])


def write_ply(path, positions, normals, uvs, faces, comment: str = "") -> None:
    """Write a triangle mesh (N×3 positions, N×3 normals, N×2 uvs, M×3 int faces) atomically, mode
    644 (readable by everyone, as a file written with the usual umask 022; ``mkstemp`` alone gives 600)."""
    P = np.asarray(positions, np.float64).reshape(-1, 3)
    N = np.asarray(normals, np.float64).reshape(-1, 3)
    UV = np.asarray(uvs, np.float64).reshape(-1, 2)
    F = np.asarray(faces, np.int64).reshape(-1, 3)
    if not (len(P) == len(N) == len(UV)) or len(F) == 0:
        raise InputError(f"PLY {path}: {len(P)} positions, {len(N)} normals, {len(UV)} uvs and {len(F)} faces; "
                         "need as many normals and uvs as positions and at least one face")
    if F.min() < 0 or F.max() >= len(P) or not np.isfinite(P).all():
        raise InputError(f"PLY {path}: face indices outside 0..{len(P) - 1} or non-finite positions")
    v = np.empty(len(P), _VERTEX)
    for k, col in enumerate("xyz"):
        v[col] = P[:, k]
        v["n" + col] = N[:, k]
    v["u"], v["v"] = UV[:, 0], UV[:, 1]
    f = np.empty(len(F), _FACE)
    f["n"] = 3
    f["i"] = F
    comment_line = "".join(f"comment {c}\n" for c in comment.splitlines() if c.strip())
    header = ("ply\nformat binary_little_endian 1.0\n" + comment_line +
              f"element vertex {len(P)}\n" + "".join(f"property float {c}\n" for c in _VERTEX.names) +
              f"element face {len(F)}\nproperty list uchar int vertex_indices\nend_header\n")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(header.encode("ascii"))
            fh.write(v.tobytes())
            fh.write(f.tobytes())
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def read_ply(path) -> dict:
    """Read a PLY written by :func:`write_ply`: {"positions", "normals", "uvs", "faces", "comments"}."""
    path = Path(path)
    data = path.read_bytes()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise InputError(f"{path} is not a PLY file (no 'ply' magic or no end_header); re-export it")
    lines = data[:end].decode("ascii").splitlines()
    if "format binary_little_endian 1.0" not in lines:
        raise InputError(f"{path}: only binary little-endian PLY files written by shadowlab are read here")
    counts = {ln.split()[1]: int(ln.split()[2]) for ln in lines if ln.startswith("element ")}
    body = data[end + len(b"end_header\n"):]
    nv, nf = counts.get("vertex", 0), counts.get("face", 0)
    if len(body) != nv * _VERTEX.itemsize + nf * _FACE.itemsize:
        raise InputError(f"{path}: truncated or not in shadowlab's layout; re-export it")
    v = np.frombuffer(body, _VERTEX, nv)
    f = np.frombuffer(body, _FACE, nf, offset=nv * _VERTEX.itemsize)
    return {"positions": np.stack([v[c] for c in "xyz"], 1), "normals": np.stack([v["n" + c] for c in "xyz"], 1),
            "uvs": np.stack([v["u"], v["v"]], 1), "faces": f["i"].astype(np.int64),
            "comments": [ln[8:] for ln in lines if ln.startswith("comment ")]}
