"""glTF 2.0 both ways (issue 26): ``shadowlab export --format gltf`` and ``scene.load("x.glb")``.

What must hold, each tested here:

* the exported ``.glb`` of contact, two_lights, street and foliage (alpha-tested cards) has no
  Khronos validator error and no warning (the real validator, ``make engines``);
* its camera casts the truth's rays: the glTF camera (node −z forward, +x right, ``yfov``,
  ``aspectRatio``) through each pixel centre gives the direction of Mitsuba's sensor ray
  (render/camera.py, itself checked against ``sensor.sample_ray``);
* lights carry the closed-form intensities of the module's table (candela = W/sr, lux = W/m²) for
  every kind, face the way the light emits, and area emitters are extras, never drawable meshes;
* an alpha-tested shape is ``MASK`` with its cut-off and the truth's binary opacity embedded;
* round trip: see :func:`test_round_trip_gives_the_same_truth_bits`;
* a glTF from elsewhere (no extras) loads with the stated defaults, printed once, and a sidecar
  changes them;
* bad input exits 2 with the fix: no lights, no camera (unless the sidecar gives one), a corrupt
  file, an unsupported feature; shadowlab's own invalid glb exits 4 and leaves ``--out`` as it was.
"""

import base64
import json
import math
import struct

import numpy as np
import pygltflib as gl
import pytest

from shadowlab import cli

SCENES_VALIDATED = ("contact", "two_lights", "street", "foliage")
RES = (64, 36)


def _main(args, capsys):
    rc = cli.main([str(a) for a in args])
    out, err = capsys.readouterr()
    return rc, out, err


def _load_gltf(path) -> gl.GLTF2:
    return gl.GLTF2().load(str(path))


@pytest.fixture(scope="module")
def exported(tmp_path_factory, mitsuba_backend):
    """name -> (glb path, manifest) of each built-in scene exported once at 64×36."""
    from shadowlab.scene import load
    from shadowlab.scene.gltf import write_glb
    d = tmp_path_factory.mktemp("glb")
    out = {}

    def get(name):
        if name not in out:
            p = d / f"{name}.glb"
            out[name] = (p, write_glb(load(name, resolution=RES), p))
        return out[name]
    return get


# -- the writer --------------------------------------------------------------------------------


@pytest.mark.parametrize("name", SCENES_VALIDATED)
def test_exported_glb_passes_the_khronos_validator(name, exported):
    from shadowlab.scene.gltf import report_lines, validate_glb
    p, manifest = exported(name)
    rep = validate_glb(p)
    issues = rep["issues"]
    assert issues["numErrors"] == 0, report_lines(rep)
    assert issues["numWarnings"] == 0, report_lines(rep)  # none to justify: any warning is a defect
    g = _load_gltf(p)
    # the manifest is the file's top-level extras, lights in the scene's order
    assert g.extras["lights"] == manifest["lights"] and g.extras["camera_node"] == manifest["camera_node"]
    assert manifest["resolution"] == list(RES)
    from shadowlab.scene import load_spec, resolve
    spec = load_spec(resolve(name))
    assert [x["name"] for x in manifest["lights"]] == [l.name for l in spec.lights]
    for x in manifest["lights"]:
        node = g.nodes[x["node"]]
        assert node.extensions["KHR_lights_punctual"]["light"] == x["light"] and node.mesh is None
    assert g.nodes[manifest["camera_node"]].camera == 0


def test_camera_casts_the_truths_pixel_rays(exported, mitsuba_backend):
    """glTF camera: direction of pixel (i, j) = node · (ndc_x·aspect·tan(yfov/2), ndc_y·tan(yfov/2), −1)."""
    from shadowlab.render.camera import Camera
    from shadowlab.scene import load
    for name in ("contact", "street"):
        p, m = exported(name)
        g = _load_gltf(p)
        node = g.nodes[m["camera_node"]]
        M = np.array(node.matrix, np.float64).reshape(4, 4).T
        pe = g.cameras[node.camera].perspective
        W, H = m["resolution"]
        ty = math.tan(pe.yfov / 2)
        j, i = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
        x = (2 * (i.ravel() + 0.5) / W - 1) * pe.aspectRatio * ty
        y = (1 - 2 * (j.ravel() + 0.5) / H) * ty
        d = np.stack([x, y, -np.ones_like(x)], 1) @ M[:3, :3].T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        cam = Camera.from_scene(load(name, resolution=RES))
        _, want = cam.pixel_rays()
        assert np.abs(d - want).max() < 1e-6      # float32 look_at of the sensor: ~1e-7
        assert np.abs(M[:3, 3] - cam.position).max() < 1e-6
        assert pe.aspectRatio == pytest.approx(W / H, rel=1e-12)
        assert (pe.znear, pe.zfar) == (cam.near, cam.far)
        ex = node.extras["shadowlab"]
        P = np.array(ex["world_to_clip"])
        c = P @ np.append(cam.position + 3.0 * want[5], 1.0)   # a point on pixel 5's ray
        assert c[0] / c[3] == pytest.approx(2 * 5.5 / W - 1, abs=1e-5)


def _every_kind_scene(tmp_path):
    from scene_builder import floor, write_scene
    lights = [
        {"name": "r", "kind": "rect", "position": [1.0, 4.0, 0.0], "target": [0.0, 0.0, 0.0], "size": [0.8, 0.4],
         "power": 100, "color": [1.0, 0.5, 0.25]},
        {"name": "d", "kind": "disk", "position": [-1.0, 4.0, 0.0], "target": [0.0, 0.0, 0.0], "radius": 0.3,
         "power": 80},
        {"name": "s", "kind": "sphere", "position": [0.0, 3.0, 2.0], "radius": 0.2, "power": 60},
        {"name": "p", "kind": "point", "position": [0.0, 3.5, -2.0], "power": 50, "range": 9.0},
        {"name": "sp", "kind": "spot", "position": [2.0, 3.0, 1.0], "target": [0.0, 0.0, 0.0], "angle": 25,
         "power": 40},
        {"name": "sun", "kind": "directional", "direction": [0.2, -1.0, 0.3], "angular_diameter": 2.0,
         "irradiance": 2.0},
        {"name": "bright", "kind": "point", "position": [1.0, 2.0, 1.0], "intensity": 3.0, "color": [2.0, 1.0, 0.5]}]
    shapes = [floor(3.0, transmittance=[0.5, 0.25, 1.0], opacity=0.5),
              {"name": "can", "type": "cylinder", "p0": [-0.6, 0.0, 0.3], "p1": [-0.6, 0.8, 0.3], "radius": 0.2}]
    return write_scene(tmp_path / "kinds.toml", name="kinds", lights=lights, shapes=shapes, resolution=(24, 24),
                       camera={"position": [0.0, 5.0, 6.0], "target": [0.0, 0.0, 0.0], "fov": 50})


def test_lights_have_the_closed_form_intensities(tmp_path, mitsuba_backend):
    """candela and lux from the scene's power (luminous efficacy 1): rect and disk L·A = Φ/π on the
    axis, sphere L·πr² = Φ/4π, delta point Φ/4π, delta spot Φ/(2π(1 − cos θ)), sun E."""
    from shadowlab.scene import load
    from shadowlab.scene.gltf import write_glb
    sc = load(str(_every_kind_scene(tmp_path)))
    m = write_glb(sc, tmp_path / "kinds.glb")
    g = _load_gltf(tmp_path / "kinds.glb")
    khr = g.extensions["KHR_lights_punctual"]["lights"]
    by = {x["name"]: (khr[x["light"]], g.nodes[x["node"]]) for x in m["lights"]}
    want = {"r": ("spot", 100 / math.pi), "d": ("spot", 80 / math.pi), "s": ("point", 60 / (4 * math.pi)),
            "p": ("point", 50 / (4 * math.pi)), "sp": ("spot", 40 / (2 * math.pi * (1 - math.cos(math.radians(25))))),
            "sun": ("directional", 2.0), "bright": ("point", 6.0)}
    for name, (typ, value) in want.items():
        light, node = by[name]
        assert light["type"] == typ and light["intensity"] == pytest.approx(value, rel=1e-12), name
        assert node.mesh is None
    assert by["bright"][0]["color"] == [1.0, 0.5, 0.25]           # a colour above 1: scaled into the intensity
    assert by["p"][0]["range"] == 9.0
    assert by["sp"][0]["spot"]["outerConeAngle"] == pytest.approx(math.radians(25))
    assert by["r"][0]["spot"] == {"innerConeAngle": 0.0, "outerConeAngle": math.pi / 2}
    # a light node emits along its −z: the direction the scene's light faces
    for name, fwd in (("r", [-1.0, -4.0, 0.0]), ("sun", [0.2, -1.0, 0.3])):
        M = np.array(by[name][1].matrix).reshape(4, 4).T
        assert np.allclose(-M[:3, 2], np.array(fwd) / np.linalg.norm(fwd), atol=1e-12)
    assert np.allclose(np.array(by["r"][1].matrix).reshape(4, 4).T[:3, 3], [1.0, 4.0, 0.0])
    # what glTF cannot say: the area light's emitter (not drawn), the sun's size, the cone, translucency
    ex = {n: node.extras["shadowlab"] for n, (_, node) in by.items()}
    assert ex["r"]["emitter"]["shape"] == "rectangle" and ex["r"]["emitter"]["drawable"] is False
    assert ex["r"]["light"]["size"] == [0.8, 0.4] and ex["s"]["emitter"]["shape"] == "sphere"
    assert ex["sun"]["angular_diameter_deg"] == 2.0 and ex["sp"]["cone_half_angle_deg"] == 25.0
    assert "emitter" not in ex["p"]
    assert len(g.meshes) == 2 and all(n.mesh is None or n.name in ("floor", "can") for n in g.nodes)
    floor = next(mt for mt in g.materials if mt.name == "floor").extras["shadowlab"]
    assert floor["tau"] == [0.75, 0.625, 1.0]
    # every kind reads back as it was: the lights' tables, the translucent caster
    back = load(str(tmp_path / "kinds.glb")).spec
    assert back.lights == sc.spec.lights
    assert [(x.transmittance, x.opacity) for x in back.shapes] == [(s.transmittance, s.opacity) for s in sc.spec.shapes]


def test_alpha_tested_shape_is_mask_with_the_truths_opacity(exported, tmp_path, mitsuba_backend):
    import mitsuba as mi
    from shadowlab.scene import load_spec, resolve
    from shadowlab.scene.textures import opacity_mask, read_alpha
    p, _ = exported("foliage")
    g = _load_gltf(p)
    spec = load_spec(resolve("foliage"))
    for s in spec.shapes:
        mat = next(mt for mt in g.materials if mt.name == s.name)
        mesh = next(me for me in g.meshes if me.name == s.name)
        assert mat.pbrMetallicRoughness.baseColorFactor == list(s.albedo) + [1.0]
        assert (mat.pbrMetallicRoughness.metallicFactor, mat.pbrMetallicRoughness.roughnessFactor) == (0.0, 1.0)
        if not s.alpha_tested:
            assert mat.alphaMode in (None, "OPAQUE") and mesh.primitives[0].attributes.TEXCOORD_0 is None
            continue
        assert mat.alphaMode == "MASK" and mat.alphaCutoff == s.alpha_cutoff
        assert mesh.primitives[0].attributes.TEXCOORD_0 is not None
        tex = g.textures[mat.pbrMetallicRoughness.baseColorTexture.index]
        smp = g.samplers[tex.sampler]
        assert (smp.magFilter, smp.minFilter, smp.wrapS, smp.wrapT) == (9728, 9728, 33071, 33071)
        bv = g.bufferViews[g.images[tex.source].bufferView]
        png = g.binary_blob()[bv.byteOffset: bv.byteOffset + bv.byteLength]
        (tmp_path / "opacity.png").write_bytes(png)
        a = np.array(mi.Bitmap(str(tmp_path / "opacity.png")), copy=True)
        want = np.asarray(opacity_mask(read_alpha(s.alpha_texture), s.alpha_cutoff)).reshape(a.shape[:2])
        assert np.array_equal(a[..., 3] == 255, want > 0.5) and set(np.unique(a[..., 3])) <= {0, 255}


# -- round trip --------------------------------------------------------------------------------


def _mesh_form(S, d):
    """S with every shape replaced by a ``ply`` shape of its export mesh (``mesh.shape_mesh``, the PLY
    ``shadowlab export`` writes), same camera, lights and materials."""
    from shadowlab.exchange.ply import write_ply
    from shadowlab.scene import build, parse
    from shadowlab.scene.gltf import camera_table, light_table
    from shadowlab.scene.mesh import shape_mesh
    shapes = []
    for s in S.spec.shapes:
        f = d / f"{s.name}.ply"
        write_ply(f, *shape_mesh(s, 64))
        t = {"name": s.name, "type": "ply", "filename": str(f), "albedo": list(s.albedo), "two_sided": s.two_sided}
        if s.alpha_tested:
            t.update(alpha_texture=s.alpha_texture, alpha_cutoff=s.alpha_cutoff)
        if s.translucent:
            t.update(transmittance=list(s.transmittance), opacity=s.opacity)
        shapes.append(t)
    doc = {"name": f"{S.name}-mesh", "camera": camera_table(S.spec.camera),
           "lights": [light_table(l) for l in S.spec.lights], "shapes": shapes}
    return build(parse(doc, str(d / "mesh_form.toml")))


def _truth(scene) -> dict:
    from shadowlab.reference.truth import visibility
    from shadowlab.render.frame import make_frame
    frame = make_frame(scene, u_strata=1)
    return {l.name: visibility(frame, l.name, k=2, min_rounds=1, max_rounds=2, seed=7).V for l in scene.spec.lights}


@pytest.mark.parametrize("name", ["contact", "foliage", "two_lights"])
def test_round_trip_gives_the_same_truth_bits(name, exported, tmp_path, mitsuba_backend):
    """What is compared, and why. The export tessellates analytic primitives (a sphere becomes 64×32
    facets), so import(export(S)) cannot be S's truth to the bit: its geometry is S's *mesh form*, S
    with each shape replaced by the PLY of the same triangulation, flat-shaded as every mesh shape
    is. So: (1) the truth of import(export(S)) equals the truth of S's mesh form bit for bit (64×36,
    seed 7, the truth's own sampler, every light): the glb loses nothing of the geometry, materials,
    camera and lights; (2) the lights and camera read back equal S's specs exactly; (3) export is a
    fixed point: export(import(export(S))) holds the same binary chunk (meshes, textures) and its
    import the same truth bits."""
    from shadowlab.scene import load
    from shadowlab.scene.gltf import read_gltf, write_glb
    S = load(name, resolution=RES)
    p, _ = exported(name)
    G = load(str(p))
    assert read_gltf(p) == G.spec
    assert G.spec.lights == S.spec.lights and G.spec.camera == S.spec.camera
    assert [(s.name, s.albedo, s.two_sided, s.alpha_cutoff) for s in G.spec.shapes] == \
           [(s.name, s.albedo, s.two_sided, s.alpha_cutoff) for s in S.spec.shapes]
    tg, tm = _truth(G), _truth(_mesh_form(S, tmp_path))
    for light in tg:
        assert tg[light].dtype == np.float32 and np.array_equal(tg[light], tm[light]), light
    assert any(np.any(v < 0.5) for v in tg.values())      # the test sees shadows, not an empty frame
    p2 = tmp_path / "again.glb"
    write_glb(G, p2)
    assert _load_gltf(p2).binary_blob() == _load_gltf(p).binary_blob()
    G2 = load(str(p2))
    t2 = _truth(G2)
    assert all(np.array_equal(t2[k], tg[k]) for k in tg)


# -- a glTF from elsewhere ---------------------------------------------------------------------


def _foreign(path, *, camera=True, lights=True, extra_required=None, mode=4, aspect=16 / 9, spot_deg=None,
             ortho=False):
    """A glTF written without shadowlab: a floor quad and a raised quad, a perspective camera
    (yfov 50°) looking down at them, a KHR point light 3 m up."""
    P = np.array([[-2, 0, -2], [2, 0, -2], [2, 0, 2], [-2, 0, 2],
                  [-0.5, 1, -0.5], [0.5, 1, -0.5], [0.5, 1, 0.5], [-0.5, 1, 0.5]], np.float32)
    F = np.array([0, 2, 1, 0, 3, 2, 4, 6, 5, 4, 7, 6], np.uint32)
    blob = P.tobytes() + F.tobytes()
    g = gl.GLTF2(asset=gl.Asset(version="2.0"), scene=0)
    g.buffers = [gl.Buffer(byteLength=len(blob))]
    g.bufferViews = [gl.BufferView(buffer=0, byteOffset=0, byteLength=P.nbytes, target=34962),
                     gl.BufferView(buffer=0, byteOffset=P.nbytes, byteLength=F.nbytes, target=34963)]
    g.accessors = [gl.Accessor(bufferView=0, componentType=5126, count=8, type="VEC3", min=[-2, 0, -2], max=[2, 1, 2]),
                   gl.Accessor(bufferView=1, componentType=5125, count=12, type="SCALAR")]
    g.materials = [gl.Material(name="grey", pbrMetallicRoughness=gl.PbrMetallicRoughness(
        baseColorFactor=[0.6, 0.6, 0.6, 1.0]), doubleSided=True)]
    g.meshes = [gl.Mesh(name="quads", primitives=[gl.Primitive(attributes=gl.Attributes(POSITION=0), indices=1,
                                                                material=0, mode=mode)])]
    g.nodes = [gl.Node(name="quads", mesh=0)]
    if camera:  # at (0, 4, 5), pitched 40° down (a rotation of −40° about x)
        g.cameras = [gl.Camera(type="perspective", perspective=gl.Perspective(yfov=math.radians(50), znear=0.05,
                                                                              aspectRatio=aspect))]
        if ortho:
            g.cameras = [gl.Camera(type="orthographic", orthographic=gl.Orthographic(xmag=2, ymag=2, znear=0.1,
                                                                                    zfar=50))]
        g.nodes.append(gl.Node(name="cam", camera=0, translation=[0, 4, 5],
                               rotation=[math.sin(math.radians(-20)), 0, 0, math.cos(math.radians(-20))]))
    if lights:
        g.extensionsUsed = ["KHR_lights_punctual"]
        light = {"type": "point", "intensity": 20.0, "name": "bulb"}
        if spot_deg is not None:
            light = {"type": "spot", "intensity": 20.0, "spot": {"outerConeAngle": math.radians(spot_deg)}}
        g.extensions = {"KHR_lights_punctual": {"lights": [light]}}
        g.nodes.append(gl.Node(name="bulb light", translation=[0.3, 3, 0.2],
                               extensions={"KHR_lights_punctual": {"light": 0}}))
    if extra_required:
        g.extensionsUsed = (g.extensionsUsed or []) + [extra_required]
        g.extensionsRequired = [extra_required]
    g.scenes = [gl.Scene(nodes=list(range(len(g.nodes))))]
    g.set_binary_blob(blob)
    g.save_binary(str(path))
    return path


def test_foreign_gltf_loads_with_stated_defaults_and_a_sidecar(tmp_path, mitsuba_backend, capsys):
    from shadowlab.render.frame import make_frame
    from shadowlab.scene import load
    p = _foreign(tmp_path / "room.glb")
    sc = load(str(p))
    err = capsys.readouterr().err
    assert "defaults used" in err and "camera.resolution = [128, 72]" in err and "bulb_light" in err
    load(str(p))
    assert "defaults used" not in capsys.readouterr().err        # once per file
    cam = sc.spec.camera
    assert cam.resolution == (128, 72) and cam.near == 0.05
    # the horizontal fov of the format from glTF's yfov at W/H: tan(fov/2) = tan(25°)·128/72
    assert math.tan(math.radians(cam.fov) / 2) == pytest.approx(math.tan(math.radians(25)) * 128 / 72, rel=1e-12)
    assert np.allclose(cam.position, [0, 4, 5])
    fwd = np.subtract(cam.target, cam.position)
    assert np.allclose(fwd / np.linalg.norm(fwd), [0, -math.sin(math.radians(40)), -math.cos(math.radians(40))])
    (light,) = sc.spec.lights
    assert (light.name, light.kind, light.intensity, light.position) == ("bulb_light", "point", 20.0, (0.3, 3.0, 0.2))
    (shape,) = sc.spec.shapes
    assert (shape.type, shape.albedo, shape.two_sided) == ("gltf", (0.6, 0.6, 0.6), True)
    gb = make_frame(sc, u_strata=1).gbuffer
    hit = gb.mask.reshape(-1)
    y = gb.to_image(gb.p)[..., 1].reshape(-1)[hit]
    assert hit.mean() > 0.1 and np.all(np.minimum(np.abs(y), np.abs(y - 1)) < 1e-4)   # the camera sees the quads
    # the sidecar: a size for the light (a sphere of 0.1 m with 200 W), the resolution, a name
    (tmp_path / "room.shadowlab.toml").write_text(
        'name = "room"\n[camera]\nresolution = [64, 36]\n[[lights]]\nname = "bulb_light"\nkind = "sphere"\n'
        'radius = 0.1\npower = 200\n', encoding="utf-8")
    s2 = load(str(p)).spec
    assert s2.name == "room" and s2.camera.resolution == (64, 36) and s2.camera.fov == pytest.approx(cam.fov)
    (l2,) = s2.lights
    assert (l2.kind, l2.radius, l2.power, l2.intensity, l2.position) == ("sphere", 0.1, 200.0, None, (0.3, 3.0, 0.2))
    # a misspelt key of the sidecar: exit 2 naming the key, its fix and the sidecar
    (tmp_path / "room.shadowlab.toml").write_text('[[lights]]\nname = "bulb_light"\nradus = 0.1\n', encoding="utf-8")
    rc, _, err = _main(["export", p, "--format", "gltf", "--out", tmp_path / "o"], capsys)
    assert rc == 2 and "radus" in err and "did you mean 'radius'" in err and "room.shadowlab.toml" in err


# -- bad input ---------------------------------------------------------------------------------


def test_gltf_without_lights_or_camera_exits_2_with_the_fix(tmp_path, capsys, mitsuba_backend):
    out = tmp_path / "out"
    p = _foreign(tmp_path / "dark.glb", lights=False)
    rc, _, err = _main(["export", p, "--format", "gltf", "--out", out], capsys)
    assert rc == 2 and "has no lights" in err and "dark.shadowlab.toml" in err and "KHR_lights_punctual" in err
    assert "Traceback" not in err
    p = _foreign(tmp_path / "blind.glb", camera=False)
    rc, _, err = _main(["export", p, "--format", "gltf", "--out", out], capsys)
    assert rc == 2 and "has no camera" in err and "[camera]" in err and "blind.shadowlab.toml" in err
    assert not out.exists()
    # the sidecar gives the camera: it loads and exports
    (tmp_path / "blind.shadowlab.toml").write_text(
        '[camera]\nposition = [0, 4, 5]\ntarget = [0, 0, 0]\nfov = 60\nresolution = [32, 32]\n', encoding="utf-8")
    rc, o, err = _main(["export", p, "--format", "gltf", "--out", out], capsys)
    assert rc == 0, err
    assert (out / "scene.glb").is_file() and "0 errors" in o


def test_corrupt_or_unsupported_gltf_exits_2_naming_it(tmp_path, capsys):
    good = _foreign(tmp_path / "good.glb").read_bytes()
    cases = {
        "truncated.glb": (good[: len(good) // 2], "truncated"),
        "noise.glb": (b"\x00" * 64, "no 'glTF' magic"),
        "v1.glb": (b"glTF" + struct.pack("<II", 1, 20) + b"\x00" * 8, "version 1"),
        "broken.gltf": (b'{"asset": {"version": "2.0"}, "nodes": [', "JSON does not parse"),
    }
    for name, (raw, what) in cases.items():
        p = tmp_path / name
        p.write_bytes(raw)
        rc, _, err = _main(["export", p, "--format", "gltf", "--out", tmp_path / "o"], capsys)
        assert rc == 2 and what in err and "Traceback" not in err, (name, err)
    p = _foreign(tmp_path / "draco.glb", extra_required="KHR_draco_mesh_compression")
    rc, _, err = _main(["export", p, "--format", "gltf", "--out", tmp_path / "o"], capsys)
    assert rc == 2 and "KHR_draco_mesh_compression" in err and "re-export" in err
    p = _foreign(tmp_path / "lines.glb", mode=1)
    rc, _, err = _main(["export", p, "--format", "gltf", "--out", tmp_path / "o"], capsys)
    assert rc == 2 and "mode LINES" in err and "TRIANGLES" in err
    p = _foreign(tmp_path / "ortho.glb", ortho=True)
    rc, _, err = _main(["export", p, "--format", "gltf", "--out", tmp_path / "o"], capsys)
    assert rc == 2 and "is orthographic" in err and "perspective" in err
    p = _foreign(tmp_path / "wide.glb", spot_deg=89)
    rc, _, err = _main(["export", p, "--format", "gltf", "--out", tmp_path / "o"], capsys)
    assert rc == 2 and "outer cone of 89.0°" in err and "wide.shadowlab.toml" in err
    (tmp_path / "wide.shadowlab.toml").write_text('[[lights]]\nname = "bulb_light"\nangle = 80\n', encoding="utf-8")
    rc, _, err = _main(["export", p, "--format", "gltf", "--out", tmp_path / "o"], capsys)
    assert rc == 0, err
    rc, _, err = _main(["export", tmp_path / "missing.glb", "--format", "gltf", "--out", tmp_path / "o2"], capsys)
    assert rc == 2 and "not found" in err


def test_cli_export_gltf_refuses_what_it_must_and_exits_4_on_its_own_invalid_glb(tmp_path, capsys, monkeypatch):
    from shadowlab.exchange import export
    out = tmp_path / "c"
    rc, o, err = _main(["export", "contact", "--format", "gltf", "--out", out, "-r", "32x18"], capsys)
    assert rc == 0 and "0 errors, 0 warnings" in o, err
    before = (out / "scene.glb").read_bytes()
    rc, _, err = _main(["export", "contact", "--format", "gltf", "--out", out], capsys)
    assert rc == 2 and "--force" in err and (out / "scene.glb").read_bytes() == before
    rc, _, err = _main(["export", "contact", "--format", "fbx", "--out", out], capsys)
    assert rc == 2 and "mitsuba, gltf" in err

    real = export.write_glb

    def broken(scene, path, **kw):   # a glb whose first accessor claims more vertices than its buffer holds
        m = real(scene, path, **kw)
        g = gl.GLTF2().load_binary(str(path))
        g.accessors[0].count *= 1000
        g.save_binary(str(path))
        return m
    monkeypatch.setattr(export, "write_glb", broken)
    rc, _, err = _main(["export", "contact", "--format", "gltf", "--out", out, "--force"], capsys)
    assert rc == 4 and "validator errors" in err and "shadowlab bug" in err
    assert (out / "scene.glb").read_bytes() == before and [f.name for f in out.iterdir()] == ["scene.glb"]


def test_glb_json_is_what_the_engines_read(exported):
    """The engines read the manifest and the conventions from the file alone."""
    p, m = exported("two_lights")
    raw = p.read_bytes()
    n = struct.unpack_from("<I", raw, 12)[0]
    doc = json.loads(raw[20: 20 + n])
    assert doc["extras"]["lights"] == m["lights"] and "conventions" in doc["extras"]["shadowlab"]
    assert doc["extensionsUsed"] == ["KHR_lights_punctual"]


def test_a_gltf_scene_exports_to_mitsuba_too(exported, tmp_path, capsys):
    """Every command takes a .glb: the Mitsuba export writes each glTF primitive as a world-space PLY
    that scene.xml loads (export's own check loads both XML files and counts their shapes)."""
    p, _ = exported("foliage")
    rc, o, err = _main(["export", p, "--out", tmp_path / "m"], capsys)
    assert rc == 0, err
    scene = json.loads((tmp_path / "m" / "scene.json").read_text())
    assert scene["scene"] == "foliage-gltf" and len(scene["files"]["source_meshes"]) == 5
    assert 'filename" value="meshes/source/card0.ply' in (tmp_path / "m" / "scene.xml").read_text()


def test_a_gltf_shape_in_a_toml_scene(tmp_path, mitsuba_backend, capsys):
    """``type = "gltf"`` takes one node's triangles into any scene, with the shape's own transform on top."""
    from shadowlab.scene import load
    from shadowlab.scene.mesh import scene_triangles
    from scene_builder import floor, write_scene
    _foreign(tmp_path / "room.glb")
    lights = [{"name": "p", "kind": "point", "position": [0.0, 3.0, 0.0], "power": 10}]
    cam = {"position": [0.0, 4.0, 6.0], "target": [0.0, 0.0, 0.0], "fov": 50}
    shape = {"name": "quads", "type": "gltf", "filename": "room.glb", "node": "quads", "translate": [0.0, 0.5, 0.0]}
    sc = load(str(write_scene(tmp_path / "s.toml", name="s", lights=lights, shapes=[floor(5.0), shape],
                              resolution=(16, 16), camera=cam)))
    tris, owner = scene_triangles(sc.spec)
    mine = tris[owner == 1]
    assert mine.shape == (4, 3, 3) and sorted(set(np.round(mine[..., 1].ravel(), 6))) == [0.5, 1.5]
    assert sc.shape_names[:2] == ["floor", "quads"]
    bad = dict(shape, node="nope")
    p = write_scene(tmp_path / "bad.toml", name="bad", lights=lights, shapes=[bad], resolution=(16, 16), camera=cam)
    rc, _, err = _main(["export", p, "--format", "gltf", "--out", tmp_path / "o"], capsys)
    assert rc == 2 and "no node 'nope'" in err and "quads" in err


def test_missing_validator_names_make_engines(tmp_path, monkeypatch, capsys, exported):
    from shadowlab.errors import EnvironmentProblem
    from shadowlab.scene import gltf
    p, _ = exported("contact")
    monkeypatch.setenv("SHADOWLAB_NODE_MODULES", str(tmp_path / "node_modules"))   # `make engines` never ran
    with pytest.raises(EnvironmentProblem, match="make engines"):
        gltf.validate_glb(p)
    assert gltf.EnvironmentProblem.exit_code == 3
    rc, o, err = _main(["export", "contact", "--format", "gltf", "--out", tmp_path / "o", "-r", "16x16"], capsys)
    assert rc == 0 and "not validated" in o and "make engines" in o and (tmp_path / "o" / "scene.glb").is_file()


def test_a_gltf_with_external_and_embedded_buffers_loads_as_the_glb(tmp_path, mitsuba_backend, capsys):
    """.gltf (JSON) with its buffer in a .bin beside it, or as a data URI, gives the .glb's triangles."""
    from shadowlab.scene import load
    from shadowlab.scene.mesh import scene_triangles
    glb = _foreign(tmp_path / "room.glb")
    want = scene_triangles(load(str(glb)).spec)[0]
    blob = gl.GLTF2().load(str(glb)).binary_blob()
    (tmp_path / "ext.bin").write_bytes(blob)
    for uri, name in (("ext.bin", "ext.gltf"),
                      ("data:application/octet-stream;base64," + base64.b64encode(blob).decode(), "uri.gltf")):
        doc = json.loads(gl.GLTF2().load(str(glb)).to_json())
        doc["buffers"][0]["uri"] = uri
        (tmp_path / name).write_text(json.dumps(doc), encoding="utf-8")
        got = scene_triangles(load(str(tmp_path / name)).spec)[0]
        assert np.array_equal(got, want), name
    (tmp_path / "ext.bin").unlink()
    rc, _, err = _main(["export", tmp_path / "ext.gltf", "--format", "gltf", "--out", tmp_path / "o"], capsys)
    assert rc == 2 and "ext.bin" in err and "beside the .gltf" in err
