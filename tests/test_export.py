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
    return {
        str(p.relative_to(d)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(d.rglob("*")) if p.is_file()
    }


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
    from scene_builder import floor, write_scene
    lights = [
        {"name": "r", "kind": "rect", "position": [1.0, 4.0, 0.0], "target": [0.0, 0.0, 0.0], "size": [0.8, 0.4],
         "power": 100, "color": [1.0, 0.5, 0.25]},
        {"name": "d", "kind": "disk", "position": [-1.0, 4.0, 0.0], "target": [0.0, 0.0, 0.0], "radius": 0.3,
         "power": 80},
        {"name": "s", "kind": "sphere", "position": [0.0, 3.0, 2.0], "radius": 0.2, "power": 60},
        {"name": "p", "kind": "point", "position": [0.0, 3.5, -2.0], "power": 50},
        {"name": "sp", "kind": "spot", "position": [2.0, 3.0, 1.0], "target": [0.0, 0.0, 0.0], "angle": 25,
         "power": 40},
        {"name": "sun", "kind": "directional", "direction": [0.2, -1.0, 0.3], "angular_diameter": 2.0,
         "irradiance": 2.0}]
    shapes = [floor(3.0),
              {"name": "puck", "type": "disk", "translate": [0.5, 0.3, 0.0], "rotate": [1, 0, 0, -90], "scale": 0.4},
              {"name": "can", "type": "cylinder", "p0": [-0.6, 0.0, 0.3], "p1": [-0.6, 0.8, 0.3], "radius": 0.2}]
    toml = write_scene(tmp_path / "kinds.toml", name="kinds", lights=lights, shapes=shapes, resolution=(24, 24),
                       camera={"position": [0.0, 5.0, 6.0], "target": [0.0, 0.0, 0.0], "fov": 50})
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
    assert np.linalg.norm(tw[:3, 0]) == pytest.approx(0.4, rel=1e-6) and np.linalg.norm(tw[:3, 1]) == pytest.approx(
        0.2, rel=1e-6
    )
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


# ---------------------------------------------------------------------------------------------
# lights.json: the shadow camera and the depth bias of `hard`; portable, world-readable exports

def _lightview_spec(tmp_path=None):
    """tests/lightview_scene.py (spot, sun, sphere, rect) plus a point light; small maps in every
    depth format."""
    import copy
    from lightview_scene import SCENE
    from shadowlab.scene import parse
    scene = copy.deepcopy(SCENE)
    scene["lights"].append({"name": "pt", "kind": "point", "position": [0.2, 2.0, 0.9], "power": 50.0})
    bits = {"spot": 16, "sun": 32, "bulb": 32, "panel": 24, "pt": 24}
    for l in scene["lights"]:
        l["shadow_map"], l["depth_bits"] = 48, bits[l["name"]]
    return parse(scene, "lightview.toml")


@pytest.fixture(scope="module")
def shadow_export(tmp_path_factory, mitsuba_backend):
    from shadowlab.exchange.export import export_scene
    from shadowlab.render.frame import make_frame
    from shadowlab.scene import build
    spec = _lightview_spec()
    out = tmp_path_factory.mktemp("shadow") / "lv"
    export_scene(spec, out)
    lights = {l["name"]: l for l in json.loads((out / "lights.json").read_text())["lights"]}
    return make_frame(build(spec), u_strata=1), lights


def _project(M, p):
    c = np.concatenate([p, np.ones((len(p), 1))], 1) @ np.asarray(M, np.float64).T
    return c[:, :3] / c[:, 3:]


def test_shadow_camera_is_the_map_hard_samples(shadow_export):
    """A world point projected with the exported matrices (Direct3D, OpenGL, Vulkan) lands where
    LightView.lookup of hard's map puts it (u, v within 1e-3 texel) with its NDC depth (OpenGL:
    (ndc.z + 1)/2); map size, format and planes are the light's."""
    import mitsuba as mi
    from shadowlab.techniques import base
    from shadowlab.techniques.shadow_map import view_for
    frame, lights = shadow_export
    hard = base.get("hard").resolve({})
    rng = np.random.default_rng(1)
    lo, hi = np.array(frame.scene.bbox_min) - 0.3, np.array(frame.scene.bbox_max) + 0.3
    box = rng.uniform(lo, hi, (4000, 3))
    dirs = rng.normal(size=(3000, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    for spec in frame.scene.spec.lights:
        cam = lights[spec.name]["shadow_camera"]
        # points in the scene's box and around the light (every cube face gets some)
        pts = np.concatenate([box, np.array(cam["faces"][0]["origin"]) + dirs * rng.uniform(0.3, 3.0, (3000, 1))])
        view = view_for(frame, spec.name, hard)
        N = view.res
        assert cam["map_size"] == [48, 48] == [N, N] and cam["depth_format"]["bits"] == spec.depth_bits == view.bits
        assert cam["faces_count"] == view.nfaces and cam["technique"] == "hard"
        assert (cam["near"], cam["far"]) == (view.proj.faces[0].near, view.proj.faces[0].far)
        rec = view.lookup(mi.Point3f(*[pts[:, k].astype(np.float32) for k in range(3)]))
        face = np.asarray(rec["face"].numpy()) if view.nfaces > 1 else np.zeros(len(pts), int)
        u, v, d = (np.asarray(rec[k].numpy(), np.float64) for k in ("u", "v", "d"))
        inside = np.asarray(rec["inside"].numpy())
        assert inside.sum() > 300, spec.name
        for k, f in enumerate(cam["faces"]):
            sel = inside & (face == k)
            assert sel.sum() >= 20, (spec.name, k)
            p = pts[sel]
            d3d = _project(f["direct3d"]["world_to_clip"], p)
            gl = _project(f["opengl"]["world_to_clip"], p)
            vk = _project(f["vulkan"]["world_to_clip"], p)
            for name, ndc, row in (("direct3d", d3d, (1 - d3d[:, 1]) / 2 * N), ("opengl", gl, (1 - gl[:, 1]) / 2 * N),
                                   ("vulkan", vk, (vk[:, 1] + 1) / 2 * N)):
                assert np.abs((ndc[:, 0] + 1) / 2 * N - u[sel]).max() < 1e-3, (spec.name, k, name)
                assert np.abs(row - v[sel]).max() < 1e-3, (spec.name, k, name)
            np.testing.assert_allclose(d3d[:, 2], d[sel], rtol=1e-5, atol=1e-6)
            np.testing.assert_allclose(vk[:, 2], d[sel], rtol=1e-5, atol=1e-6)
            np.testing.assert_allclose((gl[:, 2] + 1) / 2, d[sel], rtol=1e-5, atol=1e-6)
            for api in ("direct3d", "opengl", "vulkan"):  # the products are what they claim
                m = f[api]
                assert np.allclose(np.array(m["view_to_clip"]) @ np.array(m["world_to_view"]), m["world_to_clip"])
            # OpenGL view space looks down -z: a rotation; Direct3D's light space is left-handed
            assert np.linalg.det(np.array(f["opengl"]["world_to_view"])[:3, :3]) == pytest.approx(1.0)
            assert np.linalg.det(np.array(f["direct3d"]["world_to_view"])[:3, :3]) == pytest.approx(-1.0)


@pytest.mark.parametrize("name", ["spot", "sun", "pt"])
def test_rendering_with_the_exported_camera_gives_hards_depths(shadow_export, name):
    """The surfaces the map's texel rays hit, projected with the exported Direct3D matrices, land on
    those texel centres with the stored depth (one step of the depth format): rasterising the scene
    with this camera writes shadowlab's map."""
    import mitsuba as mi
    from shadowlab.render.lightview import texel_rays
    from shadowlab.techniques import base
    from shadowlab.techniques.shadow_map import view_for
    frame, lights = shadow_export
    view = view_for(frame, name, base.get("hard").resolve({}))
    cam = lights[name]["shadow_camera"]
    N, F = view.res, view.nfaces
    o, dirs = texel_rays(view.proj)
    f0 = view.proj.faces[0]
    o = o + dirs * (min(0.0, f0.near) if f0.ortho else 1e-5 * frame.scene.radius)  # as light_view starts them
    si = frame.scene.mi_scene.ray_intersect(mi.Ray3f(mi.Point3f(*[o[:, k].astype(np.float32) for k in range(3)]),
                                                     mi.Vector3f(*[dirs[:, k].astype(np.float32) for k in range(3)])))
    hit = np.asarray(si.is_valid().numpy())
    p = np.stack([np.asarray(c.numpy(), np.float64) for c in (si.p.x, si.p.y, si.p.z)], 1)
    assert np.array_equal(hit, view.hit.ravel())
    step = 1.0 / (2 ** view.bits - 1) if view.bits != 32 else 0.0
    jj, ii = np.meshgrid(np.arange(N), np.arange(N), indexing="ij")
    for k in range(F):
        sl = slice(k * N * N, (k + 1) * N * N)
        h = hit[sl]
        ndc = _project(cam["faces"][k]["direct3d"]["world_to_clip"], p[sl][h])
        assert np.abs((ndc[:, 0] + 1) / 2 * N - (ii.ravel()[h] + 0.5)).max() < 2e-3
        assert np.abs((1 - ndc[:, 1]) / 2 * N - (jj.ravel()[h] + 0.5)).max() < 2e-3
        # depth clamp: casters before the near plane are stored at 0 (shadow_camera.depth_clamp)
        err = np.abs(np.clip(ndc[:, 2], 0, 1) - view.depth[k].ravel()[h])
        # half a step of the format, plus the float32 hit points' round-off (largest near the near plane)
        assert err.max() <= step * 0.5 + 3e-5 and np.median(err) <= step * 0.5 + 1e-6, (name, k)
    assert "depth_clamp" in cam and "GL_DEPTH_CLAMP" in cam["depth_clamp"]


def test_cube_faces_order_and_cubemap_matrices(shadow_export):
    """Point and sphere lights: faces +X, -X, +Y, -Y, +Z, -Z, each looking down its axis; a point in
    a face's frustum projects inside that face (and shadowlab's lookup picks that face); the cubemap
    matrices put a direction at the (s, t) of the specs' face selection table, with the same depth,
    and its texels relate to shadowlab's as ``same_texels`` says."""
    import mitsuba as mi
    from shadowlab.techniques import base
    from shadowlab.techniques.shadow_map import view_for
    frame, lights = shadow_export
    order = ["+X", "-X", "+Y", "-Y", "+Z", "-Z"]
    # the face selection table of the OpenGL / Vulkan specs: major axis -> (sc, tc) as components of d
    table = {0: lambda d: (-d[2], -d[1]), 1: lambda d: (d[2], -d[1]), 2: lambda d: (d[0], d[2]),
             3: lambda d: (d[0], -d[2]), 4: lambda d: (d[0], -d[1]), 5: lambda d: (-d[0], -d[1])}
    rng = np.random.default_rng(3)
    for name in ("pt", "bulb"):
        cam = lights[name]["shadow_camera"]
        view = view_for(frame, name, base.get("hard").resolve({}))
        N = view.res
        assert cam["cube_face_order"] == order and [f["name"] for f in cam["faces"]] == order
        o = np.array(cam["faces"][0]["origin"])
        for k, f in enumerate(cam["faces"]):
            axis = np.zeros(3)
            axis[k // 2] = 1.0 if k % 2 == 0 else -1.0
            assert np.allclose(f["forward"], axis) and f["fov_deg"] == pytest.approx(90.0)
            # points inside face k's frustum: along the axis, tilted by less than 45 degrees
            t = rng.uniform(0.5, 2.0, 200)
            off = rng.uniform(-0.9, 0.9, (200, 3))
            off[:, k // 2] = 0.0
            p = o + (axis + off) * t[:, None]
            keep = (t > 1.2 * cam["near"] / 1.0)
            p = p[keep]
            for api in ("direct3d", "opengl", "vulkan"):
                ndc = _project(f[api]["world_to_clip"], p)
                assert (np.abs(ndc[:, :2]) < 1).all(), (name, k, api)
                zlo = -1 if api == "opengl" else 0
                assert ((ndc[:, 2] > zlo) & (ndc[:, 2] < 1)).all(), (name, k, api)
            rec = view.lookup(mi.Point3f(*[p[:, c].astype(np.float32) for c in range(3)]))
            assert (np.asarray(rec["face"].numpy()) == k).all()
            # cube-map sampling: direction d = p - o; (s, t) from the table; the same depth
            dvec = p - o
            ma = np.abs(dvec[:, k // 2])
            sc, tc = table[k](dvec.T)
            s, tt = (sc / ma + 1) / 2, (tc / ma + 1) / 2
            cm = f["cubemap"]
            d3d, gl, vk = (_project(cm[a]["world_to_clip"], p) for a in ("direct3d", "opengl", "vulkan"))
            np.testing.assert_allclose((gl[:, 0] + 1) / 2, s, atol=1e-9)
            np.testing.assert_allclose((gl[:, 1] + 1) / 2, tt, atol=1e-9)       # OpenGL: window row 0 = t 0
            np.testing.assert_allclose((d3d[:, 0] + 1) / 2, s, atol=1e-9)
            np.testing.assert_allclose((1 - d3d[:, 1]) / 2, tt, atol=1e-9)      # Direct3D: row 0 at the top
            np.testing.assert_allclose((vk[:, 0] + 1) / 2, s, atol=1e-9)
            np.testing.assert_allclose((vk[:, 1] + 1) / 2, tt, atol=1e-9)       # Vulkan: y down
            d = np.asarray(rec["d"].numpy(), np.float64)
            np.testing.assert_allclose(d3d[:, 2], d, rtol=1e-5)
            np.testing.assert_allclose(vk[:, 2], d, rtol=1e-5)
            np.testing.assert_allclose((gl[:, 2] + 1) / 2, d, rtol=1e-5)
            # same_texels: cube (column, row) from shadowlab's (u, v)
            u, v = (np.asarray(rec[c].numpy(), np.float64) for c in ("u", "v"))
            same = cm["same_texels"]
            col = u if same["columns"] == "same" else N - u
            row = v if same["rows"] == "same" else N - v
            assert np.abs(col - s * N).max() < 1e-3 and np.abs(row - tt * N).max() < 1e-3, (name, k, same)
            for api in ("direct3d", "opengl", "vulkan"):
                m = cm[api]
                assert np.allclose(np.array(m["view_to_clip"]) @ np.array(m["world_to_view"]), m["world_to_clip"])
    assert lights["spot"]["shadow_camera"]["cube_face_order"] is None


def test_depth_bias_in_lights_json_is_hards(shadow_export):
    from shadowlab.exchange.bias import gl_polygon_offset, vk_depth_bias
    from shadowlab.techniques import base
    _, lights = shadow_export
    hard = base.get("hard").resolve({})
    for name, l in lights.items():
        b = l["depth_bias"]
        bits = l["depth_bits"]
        assert b["technique"] == "hard" and b["depth_format"] == ("float32" if bits == 32 else f"unorm{bits}")
        assert b["direct3d"]["DepthBias"] == hard["depth_bias"] == 16
        assert b["direct3d"]["SlopeScaledDepthBias"] == hard["slope_scaled_depth_bias"] == 2.0
        assert b["receiver"]["constant_bias"] == hard["constant_bias"]
        for e in b["opengl"]:
            want = gl_polygon_offset(16, 2.0, bits, r_gl=e.get("r_preset", "step"))
            assert (e["factor"], e["units"], e["clamp"]) == tuple(want)
        for e in b["vulkan"]:
            want = vk_depth_bias(16, 2.0, bits, r_vk=e.get("r_preset", "step"))
            assert (e["depthBiasConstantFactor"], e["depthBiasSlopeFactor"], e["depthBiasClamp"]) == tuple(want)
    panel = {e["r_preset"]: e for e in lights["panel"]["depth_bias"]["opengl"]}  # 24-bit: the measured llvmpipe case
    assert (panel["mesa-llvmpipe"]["factor"], panel["mesa-llvmpipe"]["units"]) == (2.0, 8.0)


def test_export_is_portable_and_world_readable(tmp_path, mitsuba_backend):
    """Under umask 077 every exported file is 644 and every directory 755; scene.xml names its
    meshes (the scene's PLY and OBJ files, copied into meshes/source/) by relative paths that exist
    in the export, which loads as the original scene after it moved and the originals are gone."""
    import shutil
    import stat
    import xml.etree.ElementTree as ET
    import mitsuba as mi
    from shadowlab.exchange.export import export_scene
    from shadowlab.scene import load
    src = tmp_path / "user"
    src.mkdir()
    (src / "geo").mkdir()
    V = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], "<f4")
    F = [(0, 1, 2), (0, 3, 1), (0, 2, 3), (1, 3, 2)]
    head = ("ply\nformat binary_little_endian 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
            "property float z\nelement face 4\nproperty list uchar int vertex_indices\nend_header\n").encode()
    import struct
    (src / "geo" / "tet.ply").write_bytes(head + V.tobytes() + b"".join(struct.pack("<B3i", 3, *f) for f in F))
    (src / "box.obj").write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3\nf 1 3 4\n")
    (src / "scene.toml").write_text("""
name = "portable"
[camera]
position = [0.0, 3.0, 4.0]
target = [0.0, 0.3, 0.0]
fov = 50
resolution = [32, 24]
[[lights]]
name = "p"
kind = "point"
position = [0.0, 3.0, 1.0]
power = 50
shadow_map = 32
[[shapes]]
name = "floor"
type = "rectangle"
rotate = [1, 0, 0, -90]
scale = 2.0
[[shapes]]
name = "tet"
type = "ply"
filename = "geo/tet.ply"
translate = [-0.5, 0.5, 0.0]
scale = 0.3
[[shapes]]
name = "tet2"
type = "ply"
filename = "geo/tet.ply"
translate = [0.5, 0.5, 0.0]
scale = 0.2
[[shapes]]
name = "card"
type = "obj"
filename = "box.obj"
translate = [0.0, 0.2, 0.6]
scale = 0.4
""")
    out = tmp_path / "exports" / "portable"
    old = os.umask(0o077)
    try:
        m = export_scene(str(src / "scene.toml"), out)
        export_scene(str(src / "scene.toml"), out, force=True)  # replacing keeps the modes
    finally:
        os.umask(old)
    for p in [out, *out.rglob("*")]:
        mode = stat.S_IMODE(p.stat().st_mode)
        assert mode == (0o755 if p.is_dir() else 0o644), (str(p.relative_to(out)), oct(mode))
    assert m["files"]["source_meshes"] == ["meshes/source/card.obj", "meshes/source/tet.ply"]  # one copy per file
    shapes = {s["name"]: s for s in m["shapes"]}
    assert shapes["tet"]["source_mesh"] == shapes["tet2"]["source_mesh"] == "meshes/source/tet.ply"
    assert (out / "meshes/source/tet.ply").read_bytes() == (src / "geo" / "tet.ply").read_bytes()
    assert (out / "meshes/source/card.obj").read_bytes() == (src / "box.obj").read_bytes()
    for xml in ("scene.xml", "scene_mesh.xml"):
        names = [e.get("value") for e in ET.parse(out / xml).iter("string") if e.get("name") == "filename"]
        assert names and all(not os.path.isabs(n) and (out / n).is_file() for n in names), (xml, names)
        assert str(src) not in (out / xml).read_text()
    ref = load(str(src / "scene.toml"))
    boxes = {s.id(): (np.array(s.bbox().min), np.array(s.bbox().max)) for s in ref.mi_scene.shapes()}
    moved = tmp_path / "elsewhere"
    shutil.move(str(out), str(moved))
    shutil.rmtree(src)
    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        loaded = mi.load_file(str(moved / "scene.xml"), optimize=False)
    finally:
        os.chdir(cwd)
    got = {s.id(): (np.array(s.bbox().min), np.array(s.bbox().max)) for s in loaded.shapes()}
    assert set(got) == set(boxes)
    for k in boxes:
        assert np.allclose(got[k][0], boxes[k][0], atol=1e-6) and np.allclose(got[k][1], boxes[k][1], atol=1e-6), k
