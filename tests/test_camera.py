"""render/camera.py: the camera as one object, against Mitsuba's own sensor; camera.near / far in
the scene format."""

import math

import numpy as np
import pytest

from lightview_scene import SCENE
from shadowlab.errors import SceneError
from shadowlab.reference import store
from shadowlab.render.camera import Camera
from shadowlab.scene import parse
from shadowlab.scene.spec import CAMERA_FAR, CAMERA_NEAR


def _spec(**camera):
    d = dict(SCENE)
    d["camera"] = {**SCENE["camera"], **camera}
    return parse(d, "cam.toml")


@pytest.fixture(scope="module")
def scene(mitsuba_backend):
    from shadowlab.scene import build
    return build(_spec())


def test_rays_match_mitsuba_sensor_at_pixel_centres(scene):
    """64×48 (not square): origins on the near plane and directions equal sample_ray's."""
    import mitsuba as mi
    cam = Camera.from_scene(scene)
    assert cam.resolution == (64, 48)
    uv = cam.pixel_uv()
    ray, _ = scene.sensor.sample_ray(0.0, 0.5, mi.Point2f(uv[:, 0].astype(np.float32), uv[:, 1].astype(np.float32)),
                                     mi.Point2f(0.5))
    o, d = cam.pixel_rays()
    assert np.abs(np.asarray(ray.d.numpy()).T - d).max() < 1e-5
    assert np.abs(np.asarray(ray.o.numpy()).T - o).max() < 1e-5
    # the G-buffer's own order is pixel_uv's
    from shadowlab.render.camera import pixel_uv
    assert np.array_equal(cam.pixel_uv(2), pixel_uv(64, 48, 2))
    from shadowlab.scene.mesh import matrix_of
    assert np.abs(matrix_of(scene.sensor.world_transform()) - cam.camera_to_world).max() < 1e-6


@pytest.mark.parametrize("near,far", [(None, None), (0.5, 20.0)])
def test_gl_and_d3d_depth_ranges(near, far):
    cam = Camera.from_spec(_spec(**({} if near is None else {"near": near, "far": far})).camera)
    n, f = (CAMERA_NEAR, CAMERA_FAR) if near is None else (near, far)
    assert (cam.near, cam.far) == (n, f)
    for z, gl, d3d in ((n, -1.0, 0.0), (f, 1.0, 1.0)):
        p = np.append(cam.position + z * cam.forward, 1.0)
        c = cam.world_to_clip("gl") @ p
        assert c[2] / c[3] == pytest.approx(gl, abs=1e-6)
        c = cam.world_to_clip("d3d") @ p
        assert c[2] / c[3] == pytest.approx(d3d, abs=1e-6)
        assert c[3] == pytest.approx(z)
        assert cam.ndc_depth(z) == pytest.approx(d3d, abs=1e-9) and cam.ndc_depth(z, "gl") == pytest.approx(
            gl, abs=1e-9
        )
        assert cam.linear_depth(cam.ndc_depth(z)) == pytest.approx(z, rel=1e-6)
    # the D3D pair and the Mitsuba-camera-space pair are one projection
    assert np.allclose(cam.proj_d3d() @ cam.view_d3d, cam.camera_to_clip() @ cam.world_to_camera)
    # GL view space looks down -z with x to the image's right
    v = cam.view_gl @ np.append(cam.position + cam.forward + 0.1 * cam.right, 1.0)
    assert v[2] < 0 and v[0] > 0
    assert np.allclose(cam.view_gl[:3, :3] @ cam.view_gl[:3, :3].T, np.eye(3))


def test_clip_matrices_and_project_agree_at_pixel_centres():
    cam = Camera.from_spec(_spec().camera)
    rng = np.random.default_rng(1)
    px, py = rng.uniform(0, 64, 50), rng.uniform(0, 48, 50)
    z = rng.uniform(1.0, 9.0, 50)
    p = cam.unproject(px, py, z)
    for conv in ("gl", "d3d"):
        c = cam.world_to_clip(conv) @ np.c_[p, np.ones(50)].T
        ndc = c[:2] / c[3]
        assert np.allclose((ndc[0] + 1) * 32, px) and np.allclose((1 - ndc[1]) * 24, py)
    qx, qy, qz = cam.project(p)
    assert np.allclose(qx, px) and np.allclose(qy, py) and np.allclose(qz, z)
    # the ray through a pixel passes through the unprojected point at that pixel
    o, d = cam.film_rays(np.c_[px / 64, py / 48])
    t = ((p - o) * d).sum(1)
    assert np.abs(o + d * t[:, None] - p).max() < 1e-9


def test_frustum_corners_project_to_image_corners():
    cam = Camera.from_spec(_spec().camera)
    c = cam.frustum_corners(1.5, 7.0)
    assert c.shape == (8, 3)
    px, py, z = cam.project(c)
    assert np.allclose(z, [1.5] * 4 + [7.0] * 4)
    assert np.allclose(px, [0, 64, 64, 0] * 2, atol=1e-9)
    assert np.allclose(py, [48, 48, 0, 0] * 2, atol=1e-9)
    assert cam.fov_y == pytest.approx(math.degrees(2 * math.atan(math.tan(math.radians(25)) * 48 / 64)))


def test_depth_range_of_a_sphere():
    cam = Camera((0, 0, 5), (0, 0, 0), fov=60)
    assert cam.depth_range((0, 0, 0), 1.0) == pytest.approx((4.0, 6.0))
    assert cam.depth_range((0, 0, 0), 10.0)[0] == cam.near


def test_camera_near_far_in_the_scene_format():
    spec = _spec(near=0.25, far=50.0)
    assert (spec.camera.near, spec.camera.far) == (0.25, 50.0)
    assert (spec.camera.near_clip, spec.camera.far_clip) == (0.25, 50.0)
    plain = _spec()
    assert plain.camera.near is None and (plain.camera.near_clip, plain.camera.far_clip) == (CAMERA_NEAR, CAMERA_FAR)
    # the defaults leave the hash as it was; setting a plane changes it
    assert plain.digest() != spec.digest()
    assert _spec(near=0.25).digest() != plain.digest()
    from shadowlab.scene.build import sensor_dict
    assert (sensor_dict(spec.camera)["near_clip"], sensor_dict(spec.camera)["far_clip"]) == (0.25, 50.0)
    assert (sensor_dict(plain.camera)["near_clip"], sensor_dict(plain.camera)["far_clip"]) == (1e-3, 1e5)
    for bad, msg in (({"near": 0.0}, "camera.near: expected a positive"),
                     ({"far": -1.0}, "camera.far: expected a positive"),
                     ({"near": 2.0, "far": 1.0}, "camera.near < camera.far"),
                     ({"near": 2e5}, "camera.near < camera.far"),
                     ({"far": "x"}, "camera.far: expected a finite number")):
        with pytest.raises(SceneError, match=msg):
            _spec(**bad)


def test_stored_references_keep_matching_their_scenes():
    """The stored references were made before camera.near / far existed: their scene hashes hold."""
    import json
    from pathlib import Path
    from shadowlab.scene import load_spec, resolve
    metas = sorted(Path(__file__).resolve().parent.parent.glob("references/*/*/meta.json"))
    assert metas
    checked = 0
    for m in metas:
        name = m.parent.parent.name
        try:
            spec = load_spec(resolve(name))
        except SceneError:  # a reference of a scene that is not built in (bench set-ups)
            continue
        meta = json.loads(m.read_text())
        (W, H), frame = store.parse_dir_name(m.parent.name)   # <W>x<H> or <W>x<H>-f<NNNN>
        if (W, H) != tuple(spec.camera.resolution):
            continue
        if frame is not None:
            spec = spec.at_frame(frame)
        assert meta["scene_hash"] == spec.digest(), name
        checked += 1
    assert checked >= 5


def test_export_camera_json_is_the_camera(scene):
    from shadowlab.exchange.export import camera_info
    info = camera_info(scene)
    cam = Camera.from_scene(scene)
    assert np.allclose(info["world_to_clip"], cam.camera_to_clip() @ cam.world_to_camera)
    assert np.allclose(info["opengl"]["world_to_clip"], cam.world_to_clip("gl"))
    assert (info["near_clip"], info["far_clip"]) == (cam.near, cam.far)
