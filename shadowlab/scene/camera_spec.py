"""The camera of a scene file: ``[camera]`` (:class:`Camera`) and its path ``[camera.path]``
(:class:`CameraPath`, keys interpolated linearly or by Catmull-Rom splines), with the validation of
their tables. Part of the scene format of :mod:`shadowlab.scene.spec`, which re-exports these names.
"""

from __future__ import annotations

from dataclasses import dataclass

from .reader import Reader, cross, norm

#: default camera clip planes (m): the ground truth's Mitsuba sensor has always used these, so a
#: scene without ``camera.near`` / ``camera.far`` renders, exports and hashes as before they existed
CAMERA_NEAR = 1e-3
CAMERA_FAR = 1e5


@dataclass(frozen=True)
class Camera:
    position: tuple
    target: tuple
    up: tuple = (0.0, 1.0, 0.0)
    fov: float = 40.0
    resolution: tuple = (128, 128)
    near: float | None = None    # clip planes (m); None = CAMERA_NEAR / CAMERA_FAR
    far: float | None = None

    @property
    def near_clip(self) -> float:
        return CAMERA_NEAR if self.near is None else float(self.near)

    @property
    def far_clip(self) -> float:
        return CAMERA_FAR if self.far is None else float(self.far)


#: most frames of a camera path (each frame may get its own stored reference)
FRAMES_MAX = 100000
INTERPOLATIONS = ("linear", "catmull-rom")


@dataclass(frozen=True)
class CameraKey:
    """One keyframe of a camera path (or one camera of an explicit list): a frame index and the
    camera's position, target, fov and up there (each defaulting to ``[camera]``'s when not given)."""

    frame: int
    position: tuple
    target: tuple
    fov: float
    up: tuple


def _lerp(a, b, t):
    return tuple(x + (y - x) * t for x, y in zip(a, b))


def _catmull_rom(p0, p1, p2, p3, t):
    """Uniform Catmull-Rom between p1 (t = 0) and p2 (t = 1); p0, p3 are the neighbouring keys."""
    t2, t3 = t * t, t * t * t
    return tuple(0.5 * (2 * b + (-a + c) * t + (2 * a - 5 * b + 4 * c - d) * t2 + (-a + 3 * b - 3 * c + d) * t3)
                 for a, b, c, d in zip(p0, p1, p2, p3))


@dataclass(frozen=True)
class CameraPath:
    """A camera path of ``frames`` frames (README, "Scene format", camera paths).

    ``keys`` are keyframes at strictly increasing frame indices from 0 to frames − 1; frame i
    between keys k and k+1 is at t = (i − f_k)/(f_{k+1} − f_k). ``interpolation`` "linear"
    interpolates position, target and up linearly; "catmull-rom" uses the uniform Catmull-Rom
    spline through the keys (the first and last keys mirrored to give the end tangents), which
    passes through every key with a continuous velocity. fov is always interpolated linearly.
    ``explicit``: the path was given as ``[[camera.path.cameras]]``, one key per frame.

    >>> k0 = CameraKey(0, (0.0, 1.0, 5.0), (0.0, 0.0, 0.0), 40.0, (0.0, 1.0, 0.0))
    >>> k1 = CameraKey(4, (4.0, 1.0, 5.0), (0.0, 0.0, 0.0), 60.0, (0.0, 1.0, 0.0))
    >>> path = CameraPath(frames=5, keys=(k0, k1))
    >>> path.key_at(1).position, path.key_at(1).fov
    ((1.0, 1.0, 5.0), 45.0)
    """

    frames: int
    interpolation: str = "linear"
    keys: tuple = ()
    explicit: bool = False

    def key_at(self, i: int) -> CameraKey:
        """The camera of frame ``i`` (0 ≤ i < frames) as a :class:`CameraKey`."""
        ks = self.keys
        for k in ks:
            if k.frame == i:
                return k
        j = max(n for n, k in enumerate(ks) if k.frame < i)
        a, b = ks[j], ks[j + 1]
        t = (i - a.frame) / (b.frame - a.frame)
        fov = a.fov + (b.fov - a.fov) * t
        if self.interpolation == "catmull-rom":
            def pt(attr):
                p1, p2 = getattr(a, attr), getattr(b, attr)
                p0 = getattr(ks[j - 1], attr) if j > 0 else tuple(2 * x - y for x, y in zip(p1, p2))
                p3 = getattr(ks[j + 2], attr) if j + 2 < len(ks) else tuple(2 * y - x for x, y in zip(p1, p2))
                return _catmull_rom(p0, p1, p2, p3, t)
            return CameraKey(i, pt("position"), pt("target"), fov, pt("up"))
        return CameraKey(i, _lerp(a.position, b.position, t), _lerp(a.target, b.target, t), fov, _lerp(a.up, b.up, t))

CAMERA_KEYS = ("position", "target", "up", "fov", "resolution", "near", "far", "path")
PATH_KEYS = ("frames", "interpolation", "keys", "cameras")
PATH_KEY_KEYS = ("frame", "position", "target", "fov", "up")
PATH_CAMERA_KEYS = ("position", "target", "fov", "up")


def read_camera(path: str, data: dict, top: Reader) -> Camera:
    if "camera" not in data or not isinstance(data["camera"], dict):
        top.fail("camera", "a [camera] table with position, target, fov, resolution")
    c = Reader(path, "camera", data["camera"])
    c.check_keys(CAMERA_KEYS, "[camera]")
    res = c.t.get("resolution", [128, 128])
    if (not isinstance(res, list) or len(res) != 2 or
            any(isinstance(x, bool) or not isinstance(x, int) or x < 1 or x > 8192 for x in res)):
        c.fail("resolution", "[width, height] with integers in 1..8192", res)
    clip = {}
    for k in ("near", "far"):
        if c.has(k):
            clip[k] = c.num(k)
            if clip[k] <= 0:
                c.fail(k, "a positive distance in metres (a clip plane in front of the camera)", clip[k])
    near, far = clip.get("near", CAMERA_NEAR), clip.get("far", CAMERA_FAR)
    if clip and near >= far:
        c.fail("far" if "far" in clip else "near",
               f"camera.near < camera.far (near {near:g}, far {far:g}; the defaults are near = {CAMERA_NEAR:g}, "
               f"far = {CAMERA_FAR:g})", clip.get("far", clip.get("near")))
    camera = Camera(position=c.vec("position"), target=c.vec("target"), up=c.vec("up", default=(0, 1, 0)),
                    fov=c.num("fov", default=40.0, lo=1.0, hi=170.0), resolution=tuple(res), **clip)
    _check_view(c, camera.position, camera.target, camera.up, "camera.position")
    return camera


def _check_view(c: Reader, position, target, up, where: str):
    """A camera (static, a key or a frame of a path) must look somewhere and have a usable up."""
    view = [a - b for a, b in zip(target, position)]
    if norm(view) == 0:
        c.fail("target", f"a point different from {where}", list(target))
    if norm(up) == 0:
        c.fail("up", "a non-zero vector (the camera's up direction; the default is [0, 1, 0])", list(up))
    if norm(cross(up, view)) <= 1e-6 * norm(up) * norm(view):
        c.fail("up", "a vector not parallel to the view direction target − position = "
               f"[{', '.join(f'{x:g}' for x in view)}] (up fixes the camera's roll, which a vector along the view "
               "does not); e.g. [0, 0, 1] when looking straight down", list(up))


def read_camera_path(path: str, cam_table: dict, camera: Camera) -> CameraPath | None:
    """``[camera.path]``: keyframes with interpolation, or an explicit list of cameras (README,
    "Scene format"). Keys and cameras take position, target, fov and up, each defaulting to the
    static ``[camera]``'s; every frame's camera is checked like the static one."""
    if "path" not in cam_table:
        return None
    raw = cam_table["path"]
    top = Reader(path, "camera", cam_table)
    if not isinstance(raw, dict):
        top.fail("path", "a [camera.path] table (frames, interpolation, [[camera.path.keys]] or "
                 "[[camera.path.cameras]])", raw)
    r = Reader(path, "camera.path", raw)
    r.check_keys(PATH_KEYS, "[camera.path]")
    if ("keys" in raw) == ("cameras" in raw):
        r.fail("keys", "either [[camera.path.keys]] (keyframes: frame, position, target, fov, up) or "
               "[[camera.path.cameras]] (one camera per frame), not " + ("both" if "keys" in raw else "neither"))
    explicit = "cameras" in raw
    items = raw["cameras" if explicit else "keys"]
    label = "cameras" if explicit else "keys"
    if not isinstance(items, list) or not items or not all(isinstance(x, dict) for x in items):
        r.fail(label, f"a non-empty array of [[camera.path.{label}]] tables", items)
    if "frames" in raw or not explicit:
        v = raw.get("frames")
        if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= FRAMES_MAX:
            r.fail("frames", f"an integer in 1..{FRAMES_MAX} (the number of frames of the camera path; a path of N "
                   "frames has frames 0..N-1)" + (", or leave it out with [[camera.path.cameras]]" if explicit else ""),
                   v)
        frames = v
    else:
        frames = len(items)
    if explicit and frames != len(items):
        r.fail("frames", f"the number of [[camera.path.cameras]] tables ({len(items)}), one camera per frame; or "
               "leave frames out", frames)
    interp = r.str("interpolation", default="linear", choices=INTERPOLATIONS)
    keys = []
    for n, it in enumerate(items):
        k = Reader(path, f"camera.path.{label}[{n}]", it)
        k.check_keys(PATH_CAMERA_KEYS if explicit else PATH_KEY_KEYS, f"[[camera.path.{label}]]")
        if explicit:
            fr = n
        else:
            fr = k.int("frame")
            prev = keys[-1].frame if keys else None
            if prev is None and fr != 0:
                k.fail("frame", "0 (the first key of a camera path is at frame 0)", fr)
            if prev is not None and fr <= prev:
                k.fail("frame", f"a frame after the previous key's {prev} (keys are strictly increasing)", fr)
            if fr > frames - 1:
                k.fail("frame", f"a frame in 0..{frames - 1} (the path has frames = {frames})", fr)
        keys.append(CameraKey(fr, k.vec("position", default=camera.position), k.vec("target", default=camera.target),
                              k.num("fov", default=camera.fov, lo=1.0, hi=170.0), k.vec("up", default=camera.up)))
        _check_view(k, keys[-1].position, keys[-1].target, keys[-1].up, "its position")
    if keys[-1].frame != frames - 1:
        r.fail("keys", f"a last key at frame {frames - 1} = frames − 1 (the path ends on a key); the last key is at "
               f"frame {keys[-1].frame}", None)
    cp = CameraPath(frames=frames, interpolation=interp, keys=tuple(keys), explicit=explicit)
    if not explicit:
        for i in range(frames):  # interpolated frames (a spline can overshoot): the same checks per frame
            k = cp.key_at(i)
            _check_view(Reader(path, f"camera.path (frame {i})", {}), k.position, k.target, k.up, "its position")
    return cp
