"""The scene's camera as one object: matrices, clip planes, frustum slices, pixel ↔ ray ↔ world.

:class:`Camera` is built from the scene format's ``[camera]`` table and a resolution. It is the
ground truth's Mitsuba ``perspective`` sensor (:func:`shadowlab.scene.build.sensor_dict`) written
out in numpy: the G-buffer, the export's ``camera.json``, light-view fits and screen-space passes
all read it, so they agree with the truth's camera rays (tests/test_camera.py checks the rays
against ``sensor.sample_ray`` at the pixel centres of a 64×48 image).

Conventions (matrices are 4×4 numpy float64, row-major, points are column vectors:
``p' = M @ [x, y, z, 1]``):

* **Camera space** (``world_to_camera``) is Mitsuba's: the camera looks along **+z**, +y is up and
  **+x points to the image's left** (a right-handed frame). ``view_depth`` is camera-space z, the
  distance along :attr:`Camera.forward`.
* **OpenGL** (``view_gl``, ``proj_gl``): view space has x right, y up and looks down **−z**
  (right-handed); ``proj_gl`` is gluPerspective: NDC z = −1 at the near plane, +1 at the far plane.
* **Direct3D** (``view_d3d``, ``proj_d3d``): view space has x right, y up and looks down **+z**
  (left-handed); ``proj_d3d`` is XMMatrixPerspectiveFovLH: NDC z = 0 at near, 1 at far.
  ``camera_to_clip`` is the same projection applied to Mitsuba camera space (what ``camera.json``
  has always held), so ``proj_d3d @ view_d3d == camera_to_clip @ world_to_camera``.
* In both conventions NDC x runs −1 → 1 from the image's left to its right edge and NDC y −1 → 1
  from its bottom to its top; clip w is the view depth.
* **Pixels**: pixel (i, j) is column i from the left, row j from the top; continuous pixel
  coordinates put the centre of pixel (i, j) at (i + ½, j + ½); film uv = (x / W, y / H).
  The horizontal field of view ``fov`` spans the image's width (Mitsuba's ``fov_axis = "x"``),
  pixels are square: tan(fov_y/2) = tan(fov/2)·H/W.
* **Clip planes**: ``camera.near`` / ``camera.far`` of the scene file, by default
  :data:`shadowlab.scene.spec.CAMERA_NEAR` = 1e-3 m and :data:`~shadowlab.scene.spec.CAMERA_FAR`
  = 1e5 m (the truth sensor's). They only shape the depth mapping of the projection matrices and
  where a ray starts (Mitsuba starts a camera ray on the near plane); a technique that needs a
  tight depth range (cascade splits) takes :meth:`Camera.depth_range` of the scene instead.

>>> cam = Camera((0, 0, 5), (0, 0, 0), fov=90.0, width=4, height=2)
>>> [round(float(x), 6) for x in cam.forward]
[0.0, 0.0, -1.0]
>>> px, py, z = cam.project(np.array([[0.0, 0.0, 0.0]]))
>>> float(px[0]), float(py[0]), float(z[0])
(2.0, 1.0, 5.0)
>>> np.allclose(cam.unproject(px, py, z), [[0, 0, 0]])
True
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from ..scene import lights as lights_mod
from ..scene.spec import CAMERA_FAR, CAMERA_NEAR

__all__ = ["Camera"]

#: Mitsuba camera space -> OpenGL view space (x and z flip)
_MI_TO_GL = np.diag([-1.0, 1.0, -1.0, 1.0])
#: Mitsuba camera space -> Direct3D view space (x flips: image right)
_MI_TO_D3D = np.diag([-1.0, 1.0, 1.0, 1.0])


def _unit(v) -> np.ndarray:
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def pixel_uv(width: int, height: int, ss: int = 1) -> np.ndarray:
    """Film coordinates of pixel (sub-)centres in the G-buffer's point order, as numpy (N, 2):
    point ``k`` is pixel ``((k // s²) % W, (k // s²) // W)``, sub-pixel ``k % s²``.

    >>> pixel_uv(2, 1).tolist()
    [[0.25, 0.5], [0.75, 0.5]]
    """
    j, i, k = np.meshgrid(np.arange(height), np.arange(width), np.arange(ss * ss), indexing="ij")
    sx, sy = k % ss, k // ss
    u = (i + (sx + 0.5) / ss) / width
    v = (j + (sy + 0.5) / ss) / height
    return np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)


class Camera:
    """A perspective pinhole camera (see the module docstring for every convention).

    ``position``, ``target``: world points; ``up``: as the scene file gives it (made orthogonal to
    the view direction, as Mitsuba's ``look_at`` does); ``fov``: the full horizontal field of view
    in degrees; ``width`` × ``height`` pixels; ``near`` / ``far``: clip planes (m), None = the
    defaults.
    """

    def __init__(self, position, target, up=(0.0, 1.0, 0.0), fov: float = 40.0, width: int = 128,
                 height: int = 128, near: float | None = None, far: float | None = None):
        self.position = np.asarray(position, np.float64).reshape(3)
        self.target = np.asarray(target, np.float64).reshape(3)
        self.up_given = np.asarray(up, np.float64).reshape(3)
        self.fov = float(fov)
        self.width, self.height = int(width), int(height)
        self.near = CAMERA_NEAR if near is None else float(near)
        self.far = CAMERA_FAR if far is None else float(far)
        if not 0 < self.near < self.far:
            raise ValueError(f"camera clip planes: expected 0 < near < far, got near {self.near}, far {self.far}")
        f = _unit(self.target - self.position)
        up = _unit(lights_mod.up_for(tuple(f), tuple(self.up_given)))
        left = _unit(np.cross(up, f))         # Mitsuba's look_at: camera +x
        self.forward = f
        self.left = left
        self.right = -left
        self.up = np.cross(f, left)           # the camera's actual +y
        self.tan_x = math.tan(math.radians(self.fov) / 2.0)
        self.tan_y = self.tan_x * self.height / self.width

    # -- construction ------------------------------------------------------------------------
    @classmethod
    def from_spec(cls, cam, resolution=None) -> "Camera":
        """From a :class:`shadowlab.scene.spec.Camera` (``resolution`` = (W, H) overrides its own)."""
        W, H = resolution or cam.resolution
        return cls(cam.position, cam.target, cam.up, cam.fov, W, H, cam.near_clip, cam.far_clip)

    @classmethod
    def from_scene(cls, scene) -> "Camera":
        """The camera of a built :class:`shadowlab.scene.Scene` at its resolution, made once per
        scene (kept in ``scene.derived``, where it has one: every frame and cascade fit reads it)."""
        memo = getattr(scene, "derived", None)
        if memo is None:
            return cls.from_spec(scene.spec.camera, scene.resolution)
        key = ("camera", scene.spec.camera, tuple(scene.resolution))
        if key not in memo:
            memo[key] = cls.from_spec(scene.spec.camera, scene.resolution)
        return memo[key]

    def __repr__(self):
        return (f"Camera(position={self.position.tolist()}, target={self.target.tolist()}, fov={self.fov}, "
                f"{self.width}x{self.height}, near={self.near:g}, far={self.far:g})")

    @property
    def resolution(self) -> tuple:
        return (self.width, self.height)

    @property
    def aspect(self) -> float:
        return self.width / self.height

    @property
    def fov_y(self) -> float:
        """Full vertical field of view in degrees."""
        return math.degrees(2.0 * math.atan(self.tan_y))

    # -- matrices ----------------------------------------------------------------------------
    @property
    def camera_to_world(self) -> np.ndarray:
        """Mitsuba camera space -> world (columns: +x = image left, +y = up, +z = forward, position)."""
        M = np.eye(4)
        M[:3, 0], M[:3, 1], M[:3, 2], M[:3, 3] = self.left, self.up, self.forward, self.position
        return M

    @property
    def world_to_camera(self) -> np.ndarray:
        """World -> Mitsuba camera space (the inverse of :attr:`camera_to_world`)."""
        R = np.stack([self.left, self.up, self.forward])
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = R, -R @ self.position
        return M

    @property
    def view_gl(self) -> np.ndarray:
        """World -> OpenGL view space (x right, y up, looking down −z)."""
        return _MI_TO_GL @ self.world_to_camera

    @property
    def view_d3d(self) -> np.ndarray:
        """World -> Direct3D view space (x right, y up, looking down +z, left-handed)."""
        return _MI_TO_D3D @ self.world_to_camera

    def proj_gl(self, near: float | None = None, far: float | None = None) -> np.ndarray:
        """OpenGL view -> clip (gluPerspective): NDC z −1 at ``near``, +1 at ``far`` (default the
        camera's planes)."""
        n, f = self._nf(near, far)
        return np.array([[1 / self.tan_x, 0, 0, 0],
                         [0, 1 / self.tan_y, 0, 0],
                         [0, 0, (f + n) / (n - f), 2 * f * n / (n - f)],
                         [0, 0, -1, 0]], np.float64)

    def proj_d3d(self, near: float | None = None, far: float | None = None) -> np.ndarray:
        """Direct3D view -> clip (XMMatrixPerspectiveFovLH): NDC z 0 at ``near``, 1 at ``far``."""
        n, f = self._nf(near, far)
        return np.array([[1 / self.tan_x, 0, 0, 0],
                         [0, 1 / self.tan_y, 0, 0],
                         [0, 0, f / (f - n), -f * n / (f - n)],
                         [0, 0, 1, 0]], np.float64)

    def camera_to_clip(self, near: float | None = None, far: float | None = None) -> np.ndarray:
        """Mitsuba camera space -> clip with the Direct3D depth range (``camera.json``'s matrix)."""
        return self.proj_d3d(near, far) @ _MI_TO_D3D

    def world_to_clip(self, convention: str = "d3d") -> np.ndarray:
        """World -> clip in ``"d3d"`` (NDC z in [0, 1]) or ``"gl"`` (NDC z in [−1, 1])."""
        if convention == "gl":
            return self.proj_gl() @ self.view_gl
        if convention == "d3d":
            return self.proj_d3d() @ self.view_d3d
        raise ValueError(f"convention {convention!r}: expected 'd3d' or 'gl'")

    def _nf(self, near, far):
        return (self.near if near is None else float(near)), (self.far if far is None else float(far))

    def ndc_depth(self, z, convention: str = "d3d"):
        """View depth -> NDC depth (numpy or Dr.Jit): d3d 0..1, gl −1..1 from near to far."""
        n, f = self.near, self.far
        d = f / (f - n) * (1.0 - n / z)
        return d if convention == "d3d" else 2.0 * d - 1.0

    def linear_depth(self, d, convention: str = "d3d"):
        """NDC depth -> view depth (inverse of :meth:`ndc_depth`)."""
        n, f = self.near, self.far
        if convention != "d3d":
            d = (d + 1.0) * 0.5
        return n / (1.0 - d * (f - n) / f)

    # -- frustum -----------------------------------------------------------------------------
    def frustum_corners(self, z0: float, z1: float) -> np.ndarray:
        """The 8 world-space corners of the view-depth slice [z0, z1] of the view frustum, (8, 3):
        first the four at depth z0, then the four at z1, each in the order (left, bottom),
        (right, bottom), (right, top), (left, top) of the image."""
        out = []
        for z in (float(z0), float(z1)):
            for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                out.append(
                    self.position + z * (self.forward + sx * self.tan_x * self.right + sy * self.tan_y * self.up)
                )
        return np.array(out)

    def depth_range(self, center, radius: float) -> tuple:
        """(z0, z1): the view depths a sphere (e.g. the scene's bounding sphere) spans, z0 at least
        the near plane; the depth range cascade splits divide."""
        zc = float(np.dot(np.asarray(center, np.float64) - self.position, self.forward))
        return max(self.near, zc - float(radius)), max(self.near * 2, zc + float(radius))

    # -- pixels, rays, points ----------------------------------------------------------------
    def pixel_uv(self, ss: int = 1) -> np.ndarray:
        """Film uv of pixel (sub-)centres in the G-buffer's point order, (N, 2) (:func:`pixel_uv`)."""
        return pixel_uv(self.width, self.height, ss)

    def pixel_tan_alpha(self, ss: int = 1) -> float:
        """tan of the half-angle of the cone through a (sub-)pixel: half its diagonal at unit
        distance, ``√2/2 · 2·tan(fov/2) / (W·ss)`` (square pixels). Off-axis the pixel's footprint
        across the ray is smaller, so the cone still covers it [Bán 2019, §2.9]."""
        return math.sqrt(0.5) * 2.0 * self.tan_x / (self.width * ss)

    def film_directions(self, uv) -> np.ndarray:
        """Unit world directions through film points ``uv`` (N, 2)."""
        uv = np.asarray(uv, np.float64).reshape(-1, 2)
        x = (2.0 * uv[:, 0] - 1.0) * self.tan_x
        y = (1.0 - 2.0 * uv[:, 1]) * self.tan_y
        d = self.forward[None] + x[:, None] * self.right[None] + y[:, None] * self.up[None]
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def film_rays(self, uv) -> tuple:
        """World rays through film points ``uv`` (N, 2) as Mitsuba's ``sample_ray`` makes them:
        (origins, unit directions), each (N, 3); the origins lie on the near plane."""
        d = self.film_directions(uv)
        t = self.near / (d @ self.forward)
        return self.position[None] + d * t[:, None], d

    def pixel_rays(self, ss: int = 1) -> tuple:
        """Rays through pixel (sub-)centres, in the G-buffer's point order."""
        return self.film_rays(self.pixel_uv(ss))

    def view_depth(self, p) -> np.ndarray:
        """World points (N, 3) -> view depth (camera-space z, along :attr:`forward`)."""
        return (np.asarray(p, np.float64).reshape(-1, 3) - self.position) @ self.forward

    def project(self, p) -> tuple:
        """World points (N, 3) -> (px, py, view depth): continuous pixel coordinates (pixel
        centres at i + ½, y down from the top row)."""
        rel = np.asarray(p, np.float64).reshape(-1, 3) - self.position
        z = rel @ self.forward
        with np.errstate(divide="ignore", invalid="ignore"):
            x = (rel @ self.right) / (z * self.tan_x)
            y = (rel @ self.up) / (z * self.tan_y)
        return (x + 1.0) * 0.5 * self.width, (1.0 - y) * 0.5 * self.height, z

    def unproject(self, px, py, depth) -> np.ndarray:
        """Continuous pixel coordinates + view depth -> world points (N, 3) (inverse of
        :meth:`project`)."""
        px, py, z = (np.asarray(a, np.float64).reshape(-1) for a in (px, py, depth))
        x = (2.0 * px / self.width - 1.0) * self.tan_x * z
        y = (1.0 - 2.0 * py / self.height) * self.tan_y * z
        return self.position[None] + z[:, None] * self.forward[None] + x[:, None] * self.right[None] + \
            y[:, None] * self.up[None]

    def eye_unproject(self, xw, yw, ze):
        """Eq. (1) of [Giegl 2007, §3.2]: window texture coordinates (x_w, y_w) ∈ [0, 1]² (y down
        from the top row) and eye-space depth z_e -> world points, numpy (N, 3) or a Dr.Jit
        ``mi.Point3f`` for Dr.Jit inputs.

        x_e = z_e·(x_ndc − b_x)/a_x, y_e = z_e·(y_ndc − b_y)/a_y with a_x, b_x, a_y, b_y read from
        :meth:`proj_d3d` (P[0][0], P[0][2], P[1][1], P[1][2]) and the viewport map x_ndc = 2x_w − 1,
        y_ndc = 1 − 2y_w (the printed second matrix of Eq. (1) has that map's offsets garbled);
        then Direct3D view space (x right, y up, z forward) -> world."""
        P = self.proj_d3d()
        ax, bx, ay, by = float(P[0, 0]), float(P[0, 2]), float(P[1, 1]), float(P[1, 2])
        xe = ze * ((2.0 * xw - 1.0 - bx) / ax)
        ye = ze * ((1.0 - 2.0 * yw - by) / ay)
        if isinstance(ze, dr.ArrayBase):
            o, r, u, f = (
                mi.Vector3f(*[float(c) for c in v]) for v in (self.position, self.right, self.up, self.forward)
            )
            return mi.Point3f(o + r * xe + u * ye + f * ze)
        xe, ye, ze = (np.asarray(a, np.float64).reshape(-1, 1) for a in (xe, ye, ze))
        return self.position[None] + xe * self.right[None] + ye * self.up[None] + ze * self.forward[None]

    def pixel_footprint(self, depth) -> np.ndarray:
        """World size of one pixel at view depth ``depth`` (square pixels)."""
        return 2.0 * self.tan_x * np.asarray(depth, np.float64) / self.width
