"""``shadowlab export``: Mitsuba XML, PLY meshes, camera.json and lights.json.

* camera.json's matrices reproduce Mitsuba's camera rays through the pixel centres (both the
  Mitsuba-camera-space / D3D-depth pair and the OpenGL pair), and project the G-buffer's hit
  points back onto the pixel centres;
* scene.xml loads with ``mi.load_file`` and renders the same image as the scene it came from
  (same seed, same samples: equal up to float round-off), for analytic primitives, a capped
  cylinder, a cube, alpha-tested cards and two lights;
* scene_mesh.xml (every shape its PLY) sees the same surfaces: camera-ray hit distances agree to
  the tessellation's sagitta, and the rendered mean to 1 %;
* every PLY is consistent (unit normals, counter-clockwise winding around them, curved surfaces
  inscribed) and lights.json's sizes, areas and radiance follow the scene file for every light kind;
* bad input exits 2 and leaves an existing export untouched.
"""

import hashlib
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from shadowlab.errors import InputError
from shadowlab.scene.mesh import sagitta
from shadowlab.exchange.ply import read_ply

ROOT = Path(__file__).resolve().parents[1]
RES = (64, 48)  # not square: a swapped aspect ratio, fov axis or W/H shows


def _digest(d: Path) -> dict:
    return {str(p.relative_to(d)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(d.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def exported(tmp_path_factory, mitsuba_backend):
    from shadowlab.exchange.export import export_scene
    tmp = tmp_path_factory.mktemp("export")
    out = {}
    for name in ("contact", "foliage", "two_lights", "parallel_planes"):
        out[name] = tmp / name
        export_scene(name, out[name], resolution=RES)
    return out


def _render(mi_scene, spp=16, seed=5):
    import mitsuba as mi
    return np.asarray(mi.render(mi_scene, spp=spp, seed=seed, integrator=mi.load_dict({"type": "direct"})), np.float64)


def _camera_rays(sensor, W, H):
    import mitsuba as mi
    j, i = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    uv = mi.Point2f(((i.ravel() + 0.5) / W).astype(np.float32), ((j.ravel() + 0.5) / H).astype(np.float32))
    ray, _ = sensor.sample_ray(0.0, 0.5, uv, mi.Point2f(0.5))
    return ray, np.asarray(ray.o.numpy()).T, np.asarray(ray.d.numpy()).T, i.ravel(), j.ravel()


@pytest.mark.parametrize("name", ["contact", "two_lights", "parallel_planes"])
def test_camera_json_reproduces_mitsuba_camera_rays(exported, name):
    from shadowlab.scene import load
    cam = json.loads((exported[name] / "camera.json").read_text())
    W, H = cam["resolution"]
    assert (W, H) == RES and cam["fov_axis"] == "x"
    sc = load(name, resolution=RES)
    ray, o, d, i, j = _camera_rays(sc.sensor, W, H)
    x, y = 2 * (i + 0.5) / W - 1, 1 - 2 * (j + 0.5) / H
    for key, z0, z1 in (("world_to_clip", 0.0, 0.999), ("opengl", -1.0, 0.999)):
        M = np.array(cam["world_to_clip"] if key == "world_to_clip" else cam["opengl"]["world_to_clip"])
        inv = np.linalg.inv(M)

        def unproject(z):
            c = np.stack([x, y, np.full_like(x, z), np.ones_like(x)], 1) @ inv.T
            return c[:, :3] / c[:, 3:]

        near = unproject(z0)
        dd = unproject(z1) - near
        dd /= np.linalg.norm(dd, axis=1, keepdims=True)
        assert np.abs(dd - d).max() < 1e-5, key
        # Mitsuba's perspective rays start on the near plane: ndc z = 0 (D3D) / -1 (OpenGL)
        assert np.abs(near - o).max() < 1e-5, key
    # the matrices are the products they claim to be
    w2c, P = np.array(cam["world_to_camera"]), np.array(cam["camera_to_clip"])
    assert np.allclose(P @ w2c, cam["world_to_clip"])
    assert np.allclose(np.linalg.inv(w2c), cam["camera_to_world"], atol=1e-6)
    gl = cam["opengl"]
    assert np.allclose(np.array(gl["view_to_clip"]) @ np.array(gl["world_to_view"]), gl["world_to_clip"])
    # camera space looks along +z, +y up, +x toward the image's left; rigid and right-handed
    fwd = np.array(cam["target"]) - np.array(cam["position"])
    fwd /= np.linalg.norm(fwd)
    assert np.allclose(w2c[:3, :3] @ fwd, [0, 0, 1], atol=1e-6)
    assert np.isclose(np.linalg.det(w2c[:3, :3]), 1.0, atol=1e-5)
    assert np.allclose(w2c[:3, :3] @ cam["position"] + w2c[:3, 3], 0, atol=1e-5)
    dc = d @ w2c[:3, :3].T  # ray directions in camera space
    row = j == H // 2
    assert (np.diff(dc[row, 0]) < 0).all()  # moving right in the image is moving to camera -x
    col = i == W // 2
    assert (np.diff(dc[col, 1]) < 0).all()  # moving down the image is moving to camera -y
    # OpenGL view space: looks along -z, x right, y up (a rotation of Mitsuba's camera space)
    w2v = np.array(gl["world_to_view"])
    assert np.allclose(w2v[:3, :3] @ fwd, [0, 0, -1], atol=1e-6)
    assert np.isclose(np.linalg.det(w2v[:3, :3]), 1.0, atol=1e-5)
    assert (np.diff((d @ w2v[:3, :3].T)[row, 0]) > 0).all()
    # the field of view is horizontal; the vertical one follows from the aspect ratio
    tx = math.tan(math.radians(cam["fov_deg"]) / 2)
    assert math.tan(math.radians(cam["fov_y_deg"]) / 2) == pytest.approx(tx * H / W)
    edge = np.abs(dc[row, 0] / dc[row, 2]).max()  # the outermost pixel centres: (1 - 1/W) of the half-width
    assert edge == pytest.approx(tx * (1 - 1 / W), rel=1e-5)
    # D3D depth: 0 on the near plane, 1 on the far plane; w = camera-space z
    for z, ndc_z in ((cam["near_clip"], 0.0), (cam["far_clip"], 1.0)):
        c = P @ [0.3 * z, -0.2 * z, z, 1]
        assert c[3] == pytest.approx(z) and c[2] / c[3] == pytest.approx(ndc_z, abs=1e-9)
    # the hit points project onto the pixel centres, with depth in [0, 1]
    si = sc.mi_scene.ray_intersect(ray)
    hit = np.asarray(si.is_valid().numpy())
    p = np.asarray(si.p.numpy()).T[hit]
    c = np.concatenate([p, np.ones((len(p), 1))], 1) @ np.array(cam["world_to_clip"]).T
    ndc = c[:, :3] / c[:, 3:]
    px, py = (ndc[:, 0] + 1) / 2 * W, (1 - ndc[:, 1]) / 2 * H
    assert np.abs(px - (i[hit] + 0.5)).max() < 1e-3 and np.abs(py - (j[hit] + 0.5)).max() < 1e-3
    assert (ndc[:, 2] > 0).all() and (ndc[:, 2] < 1).all()


@pytest.mark.parametrize("name", ["contact", "foliage", "two_lights"])
def test_scene_xml_renders_the_same_as_the_original(exported, name):
    import mitsuba as mi
    from shadowlab.scene import load
    sc = load(name, resolution=RES)
    loaded = mi.load_file(str(exported[name] / "scene.xml"), optimize=False)
    assert sorted(s.id() for s in loaded.shapes()) == sorted(s.id() for s in sc.mi_scene.shapes())
    for a, b in zip(sorted(sc.mi_scene.shapes(), key=lambda s: s.id()), sorted(loaded.shapes(), key=lambda s: s.id())):
        assert np.allclose(np.array(a.bbox().min), np.array(b.bbox().min), atol=1e-6)
        assert np.allclose(np.array(a.bbox().max), np.array(b.bbox().max), atol=1e-6)
        assert a.is_emitter() == b.is_emitter()
    ref, got = _render(sc.mi_scene), _render(loaded)
    assert ref.max() > 0
    assert np.abs(got - ref).max() <= 1e-3 * ref.max()
    assert got.mean() == pytest.approx(ref.mean(), rel=1e-5)
    # the film resolution and sample count are XML parameters
    small = mi.load_file(str(exported[name] / "scene.xml"), resx=8, resy=6, spp=2)
    assert tuple(small.sensors()[0].film().size()) == (8, 6)


@pytest.mark.parametrize("name", ["contact", "two_lights"])
def test_scene_mesh_xml_sees_the_same_surfaces(exported, name):
    import mitsuba as mi
    from shadowlab.scene import load
    sc = load(name, resolution=RES)
    mesh = mi.load_file(str(exported[name] / "scene_mesh.xml"), optimize=False)
    manifest = json.loads((exported[name] / "scene.json").read_text())
    ray, _, _, _, _ = _camera_rays(sc.sensor, *RES)
    a, b = sc.mi_scene.ray_intersect(ray), mesh.ray_intersect(ray)
    ha, hb = np.asarray(a.is_valid().numpy()), np.asarray(b.is_valid().numpy())
    assert (ha == hb).mean() >= 0.98  # silhouettes of curved shapes may differ by a pixel
    both = ha & hb
    ta, tb = np.asarray(a.t.numpy())[both], np.asarray(b.t.numpy())[both]
    # curved surfaces are inscribed: at most one sagitta of the largest radius (0.6 m) inside,
    # more only at grazing angles
    gap = 0.6 * manifest["tessellation"]["max_relative_deviation"]
    assert np.quantile(np.abs(tb - ta), 0.98) <= 4 * gap + 1e-5
    assert (tb >= ta - 1e-4).mean() > 0.99  # the mesh lies inside the primitive, never before it
    ra, rb = _render(sc.mi_scene, spp=32), _render(mesh, spp=32)
    assert rb.mean() == pytest.approx(ra.mean(), rel=0.01)


def test_ply_meshes_are_consistent(exported):
    d = exported["contact"]
    manifest = json.loads((d / "scene.json").read_text())
    shapes = {s["name"]: s for s in manifest["shapes"]}
    assert set(shapes) == {"floor", "box", "ball", "pole"}
    s = manifest["tessellation"]["segments"]
    for name, entry in shapes.items():
        m = read_ply(d / entry["ply"])
        P, N, F = m["positions"].astype(np.float64), m["normals"].astype(np.float64), m["faces"]
        assert len(F) == entry["triangles"] and len(P) == entry["vertices"]
        assert np.allclose(np.linalg.norm(N, axis=1), 1, atol=1e-5)
        g = np.cross(P[F[:, 1]] - P[F[:, 0]], P[F[:, 2]] - P[F[:, 0]])
        assert (np.einsum("ij,ij->i", g, N[F].sum(1)) > 0).all(), name  # counter-clockwise around the normals
        area = 0.5 * np.linalg.norm(g, axis=1).sum()
        if name == "floor":
            assert area == pytest.approx(64.0, rel=1e-5)  # scale 4: 8 m × 8 m
            assert np.allclose(N, [0, 1, 0], atol=1e-6)
        if name == "box":
            assert area == pytest.approx(6.0, rel=1e-5)  # 1 m cube
        if name == "ball":  # center (0.8, 0.6, 0.6), radius 0.6: inscribed, normals radial
            r = np.linalg.norm(P - [0.8, 0.6, 0.6], axis=1)
            assert np.allclose(r, 0.6, atol=1e-5)
            assert np.allclose(N, (P - [0.8, 0.6, 0.6]) / r[:, None], atol=1e-5)
            exact = 4 * math.pi * 0.36
            assert exact * (1 - 3 * sagitta(s)) < area < exact
        if name == "pole":  # radius 0.04, length 1.6, with two caps
            exact = 2 * math.pi * 0.04 * 1.6 + 2 * math.pi * 0.04 ** 2
            assert exact * (1 - 3 * sagitta(s)) < area < exact
            assert P[:, 1].min() == pytest.approx(0.0, abs=1e-6) and P[:, 1].max() == pytest.approx(1.6, abs=1e-6)
    # the light's PLY is the rectangle of lights.json, facing its target
    lights = json.loads((d / "lights.json").read_text())["lights"]
    (key,) = lights
    m = read_ply(d / key["ply"])
    P, F = m["positions"].astype(np.float64), m["faces"]
    g = np.cross(P[F[:, 1]] - P[F[:, 0]], P[F[:, 2]] - P[F[:, 0]])
    assert 0.5 * np.linalg.norm(g, axis=1).sum() == pytest.approx(key["area_m2"], rel=1e-5)
    assert np.allclose(g / np.linalg.norm(g, axis=1, keepdims=True), key["direction"], atol=1e-5)


def test_lights_json_for_every_light_kind(tmp_path, mitsuba_backend):
    """Every kind exports, loads back and renders as the original; sizes and emission as documented."""
    import mitsuba as mi
    from shadowlab.exchange.export import export_scene
    from shadowlab.scene import load
    text = """
name = "kinds"
[camera]
position = [0.0, 5.0, 6.0]
target = [0.0, 0.0, 0.0]
fov = 50
resolution = [24, 24]
[[lights]]
name = "r"
kind = "rect"
position = [1.0, 4.0, 0.0]
target = [0.0, 0.0, 0.0]
size = [0.8, 0.4]
power = 100
color = [1.0, 0.5, 0.25]
[[lights]]
name = "d"
kind = "disk"
position = [-1.0, 4.0, 0.0]
target = [0.0, 0.0, 0.0]
radius = 0.3
power = 80
[[lights]]
name = "s"
kind = "sphere"
position = [0.0, 3.0, 2.0]
radius = 0.2
power = 60
[[lights]]
name = "p"
kind = "point"
position = [0.0, 3.5, -2.0]
power = 50
[[lights]]
name = "sp"
kind = "spot"
position = [2.0, 3.0, 1.0]
target = [0.0, 0.0, 0.0]
angle = 25
power = 40
[[lights]]
name = "sun"
kind = "directional"
direction = [0.2, -1.0, 0.3]
angular_diameter = 2.0
irradiance = 2.0
[[shapes]]
name = "floor"
type = "rectangle"
rotate = [1, 0, 0, -90]
scale = 3.0
[[shapes]]
name = "puck"
type = "disk"
translate = [0.5, 0.3, 0.0]
rotate = [1, 0, 0, -90]
scale = 0.4
[[shapes]]
name = "can"
type = "cylinder"
p0 = [-0.6, 0.0, 0.3]
p1 = [-0.6, 0.8, 0.3]
radius = 0.2
"""
    toml = tmp_path / "kinds.toml"
    toml.write_text(text)
    out = tmp_path / "kinds"
    m = export_scene(str(toml), out)
    lj = json.loads((out / "lights.json").read_text())
    lights = {l["name"]: l for l in lj["lights"]}
    r = lights["r"]
    # physical_size: metres for area lights, radians for the sun; the file says which
    assert r["physical_size"] == pytest.approx(math.sqrt(0.32)) and lights["d"]["physical_size"] == pytest.approx(0.6)
    assert lights["sun"]["physical_size"] == pytest.approx(math.radians(2.0)) and lights["p"]["physical_size"] == 0
    assert "RADIANS" in lj["convention"]["physical_size"]
    assert {"ply", "albedo", "two_sided"} <= set(m["convention"])
    assert r["size"] == {"width": 0.8, "height": 0.4} and r["area_m2"] == pytest.approx(0.32)
    L = 100 / (math.pi * 0.32)
    assert r["emission"]["quantity"] == "radiance" and r["emission"]["value"] == pytest.approx(L)
    assert r["emission"]["rgb"] == pytest.approx([L, L / 2, L / 4])
    pose = np.array(r["pose"])
    assert np.allclose(pose[:3, :3].T @ pose[:3, :3], np.eye(3), atol=1e-6)  # rigid
    assert np.allclose(pose[:3, 3], [1, 4, 0], atol=1e-6)
    assert np.allclose(pose[:3, 2], -np.array([1.0, 4.0, 0.0]) / math.sqrt(17), atol=1e-6)  # faces the target
    tw = np.array(r["to_world"])
    assert np.linalg.norm(tw[:3, 0]) == pytest.approx(0.4, rel=1e-6) and np.linalg.norm(tw[:3, 1]) == pytest.approx(0.2, rel=1e-6)
    assert lights["d"]["size"] == {"radius": 0.3} and lights["d"]["area_m2"] == pytest.approx(math.pi * 0.09)
    assert lights["s"]["emission"]["value"] == pytest.approx(60 / (math.pi * 4 * math.pi * 0.04))
    assert lights["p"]["delta"] and lights["p"]["ply"] is None
    assert lights["p"]["emission"] == {"quantity": "intensity", "value": pytest.approx(50 / (4 * math.pi)),
                                       "rgb": pytest.approx([50 / (4 * math.pi)] * 3)}
    assert lights["sp"]["size"]["cone_half_angle_deg"] == 25 and lights["sp"]["delta"]
    sun = lights["sun"]
    assert sun["size"]["angular_diameter_rad"] == pytest.approx(math.radians(2.0))
    assert sun["size"]["disk_radius"] / sun["size"]["disk_distance"] == pytest.approx(math.tan(math.radians(1.0)))
    assert np.allclose(sun["direction"], np.array([0.2, -1, 0.3]) / np.linalg.norm([0.2, -1, 0.3]))
    assert sun["emission"]["value"] == pytest.approx(2.0 / (math.pi * math.sin(math.radians(1.0)) ** 2))
    assert {l["name"] for l in lights.values() if l["ply"]} == {"r", "d", "s", "sun"}
    assert len(m["files"]["meshes"]) == 3 + 4
    # the XML renders as the original
    sc = load(str(toml))
    loaded = mi.load_file(str(out / "scene.xml"), optimize=False)
    ref, got = _render(sc.mi_scene, spp=8), _render(loaded, spp=8)
    assert np.abs(got - ref).max() <= 1e-3 * ref.max()


def test_export_refuses_to_overwrite_and_force_keeps_other_files(exported, tmp_path):
    from shadowlab.exchange.export import export_scene
    d = tmp_path / "pp"
    export_scene("parallel_planes", d, resolution=RES)
    before = _digest(d)
    with pytest.raises(InputError, match="--force"):
        export_scene("parallel_planes", d, resolution=(16, 16))
    assert _digest(d) == before
    (d / "notes.txt").write_text("mine")
    (d / "meshes" / "stale.ply").write_text("old")
    export_scene("parallel_planes", d, resolution=(16, 16), force=True)
    assert (d / "notes.txt").read_text() == "mine"
    assert not (d / "meshes" / "stale.ply").exists()
    assert json.loads((d / "camera.json").read_text())["resolution"] == [16, 16]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary directory left
    with pytest.raises(InputError, match="segments"):
        export_scene("parallel_planes", tmp_path / "x", segments=2)
    assert not (tmp_path / "x").exists()


def test_export_cli(tmp_path):
    def cli(*args):
        return subprocess.run([sys.executable, "-m", "shadowlab.cli", *args], capture_output=True, text=True,
                              cwd=ROOT, timeout=600, env=dict(os.environ))
    out = tmp_path / "a"
    r = cli("export", "analytic_sphere", "--out", str(out), "--resolution", "48x40", "--segments", "32")
    assert r.returncode == 0, r.stderr
    assert "exported analytic_sphere (48x40" in r.stdout
    m = json.loads((out / "scene.json").read_text())
    assert m["resolution"] == [48, 40] and m["tessellation"]["segments"] == 32
    from shadowlab.scene import load_spec, resolve
    assert m["scene_hash"] == load_spec(resolve("analytic_sphere")).with_resolution(48, 40).digest()
    before = _digest(out)
    r = cli("export", "analytic_sphere", "--out", str(out))
    assert r.returncode == 2 and "--force" in r.stderr
    assert _digest(out) == before
    r = cli("export", "no_such_scene", "--out", str(tmp_path / "b"))
    assert r.returncode == 2 and "unknown scene" in r.stderr and not (tmp_path / "b").exists()


def test_export_refuses_sdf_only_objects(tmp_path, mitsuba_backend):
    """[[sdf]] objects have no mesh and no Mitsuba shape: refused with exit-2 InputError, nothing written."""
    from shadowlab.exchange.export import export_scene
    from shadowlab.scene.spec import builtin_names, load_spec, resolve
    sdf_scenes = [n for n in builtin_names() if getattr(load_spec(resolve(n)), "sdf", ())]
    if not sdf_scenes:
        pytest.skip("no built-in scene with [[sdf]] objects")
    with pytest.raises(InputError, match=r"\[\[sdf\]\]"):
        export_scene(sdf_scenes[0], tmp_path / "sdf")
    assert not (tmp_path / "sdf").exists()
