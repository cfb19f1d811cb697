"""Alpha-tested casters ([Buljan 2020, §2.4]): texels whose alpha is below the cut-off
are transparent to every ray: camera rays (G-buffer), light-view depth rays (shadow maps) and
the ground truth's shadow rays.

The scene: a delta point light over a planar leaf card (a rotated, non-square rectangle with
the built-in leaf texture at 32×32 texels) over a floor, 96² pixels. Exact visibility comes
from numpy alone: the card is the quad c + x·a + y·b (|x|, |y| ≤ 1), a ray meets it where
[a b −d]·(x, y, t) = o − c, uv = ((x + 1)/2, (y + 1)/2), texel (⌊u·W⌋, ⌊v·H⌋) (row 0 = the image's
top row), opaque where alpha ≥ cutoff (the generator's uint8 alpha, not read back by Mitsuba).
"""

import json
import math
from pathlib import Path

import numpy as np
import pytest

from shadowlab.errors import SceneError
from shadowlab.scene import load_spec, parse, resolve
from shadowlab.scene.textures import leaf_alpha, write_leaf_png
from shadowlab.techniques.base import get

TEX = 32
LIGHT = (0.3, 4.0, 0.2)
CARD = {"translate": [0.1, 1.5, -0.1], "rotate": [[0, 1, 0, 20], [1, 0, 0, -90]], "scale": [1.2, 1.0, 1.0]}


def scene_dict(cutoff=0.5, texture="leaf.png"):
    return {
        "name": "alpha_card",
        "camera": {"position": [0.0, 5.5, 2.0], "target": [0.0, 0.0, 0.0], "fov": 50, "resolution": [96, 96]},
        "lights": [{"name": "p", "kind": "point", "position": list(LIGHT), "power": 100.0, "shadow_map": 1024}],
        "shapes": [
            {"name": "floor", "type": "rectangle", "rotate": [1, 0, 0, -90], "scale": 3.0},
            {"name": "card", "type": "rectangle", **CARD, "albedo": [0.2, 0.5, 0.1],
             "alpha_texture": texture, "alpha_cutoff": cutoff},
        ],
    }


def _rot(axis, deg):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = math.radians(deg)
    return np.eye(3) + math.sin(t) * K + (1 - math.cos(t)) * K @ K


def card_axes():
    """Centre and the two half-axes (world) of the card: local (x, y, 0) ↦ c + x·a + y·b."""
    R = np.eye(3)
    for q in CARD["rotate"]:
        R = R @ _rot(q[:3], q[3])
    S = np.diag(CARD["scale"])
    M = R @ S
    return np.array(CARD["translate"], float), M[:, 0], M[:, 1]


def card_hit(o, d):
    """Ray o + t·d (numpy (N, 3)) against the card: (t, u, v, inside); t = inf where parallel."""
    c, a, b = card_axes()
    A = np.stack([np.broadcast_to(a, d.shape), np.broadcast_to(b, d.shape), -d], axis=2)  # (N, 3, 3) columns
    det = np.linalg.det(A)
    ok = np.abs(det) > 1e-12
    sol = np.zeros_like(d)
    sol[ok] = np.linalg.solve(A[ok], (o - c)[ok][..., None])[..., 0]
    x, y, t = sol[:, 0], sol[:, 1], np.where(ok, sol[:, 2], np.inf)
    inside = ok & (np.abs(x) <= 1) & (np.abs(y) <= 1)
    return t, (x + 1) / 2, (y + 1) / 2, inside


def texel_lookup(alpha_u8, u, v, cutoff):
    """(opaque, distance to the nearest texel edge in texels) at uv."""
    H, W = alpha_u8.shape
    fu, fv = np.clip(u, 0, 1) * W, np.clip(v, 0, 1) * H
    iu, iv = np.clip(np.floor(fu).astype(int), 0, W - 1), np.clip(np.floor(fv).astype(int), 0, H - 1)
    opaque = alpha_u8[iv, iu] / 255.0 >= np.float32(cutoff)
    edge = np.minimum(np.minimum(fu - np.floor(fu), np.ceil(fu) - fu), np.minimum(fv - np.floor(fv), np.ceil(fv) - fv))
    return opaque, edge


@pytest.fixture(scope="module")
def texdir(tmp_path_factory):
    d = tmp_path_factory.mktemp("alpha")
    alpha = write_leaf_png(d / "leaf.png", size=TEX)
    return d, alpha


@pytest.fixture(scope="module")
def frames(mitsuba_backend, texdir):
    """cutoff -> (frame, truth V image), built once each."""
    from shadowlab.reference.truth import visibility
    from shadowlab.render.frame import make_frame
    from shadowlab.scene import build
    d, _ = texdir
    cache = {}

    def get_frame(cutoff):
        if cutoff not in cache:
            scene = build(parse(scene_dict(cutoff), str(d / "alpha_card.toml")))
            frame = make_frame(scene, u_strata=1)
            cache[cutoff] = (frame, visibility(frame, "p").V)
        return cache[cutoff]
    return get_frame


def exact_visibility(frame, alpha_u8, cutoff):
    """Per pixel: (V exact, under the card, distance to a texel edge) for the floor points."""
    gb = frame.gbuffer
    p = np.stack([a.numpy() for a in (gb.p.x, gb.p.y, gb.p.z)], 1).astype(np.float64)
    d = np.asarray(LIGHT) - p
    t, u, v, inside = card_hit(p, d)
    under = inside & (t > 1e-6) & (t < 1)
    opaque, edge = texel_lookup(alpha_u8, u, v, cutoff)
    V = np.where(under & opaque, 0.0, 1.0)
    shp = (gb.height, gb.width)
    return V.reshape(shp), under.reshape(shp), np.where(under, edge, 1.0).reshape(shp)


def floor_mask(frame):
    return frame.gbuffer.shape_id[..., 0] == frame.scene.shape_names.index("floor")


# ---------------------------------------------------------------------------------------------

def test_truth_sees_through_transparent_texels(frames, texdir):
    """Measured: 0 of the 8112 floor pixels differ from the numpy visibility (2411 in holes,
    579 under leaves); the bound allows pixels within 1e-3 texel of a texel edge, where float32
    rounding may pick the neighbouring texel."""
    _, alpha = texdir
    frame, V = frames(0.5)
    Vx, under, edge = exact_visibility(frame, alpha, 0.5)
    fl = floor_mask(frame)
    assert set(np.unique(V[fl])) <= {0.0, 1.0}
    wrong = fl & (V != Vx)
    assert np.all(edge[wrong] < 1e-3), "a mismatch away from a texel edge"
    assert wrong.sum() <= 0.001 * fl.sum()
    # the card's shadow has both: holes (lit) and leaves (shadowed)
    holes, leaves = fl & under & (Vx == 1), fl & under & (Vx == 0)
    assert holes.sum() > 300 and leaves.sum() > 300
    assert np.all(V[holes & (edge > 1e-3)] == 1.0) and np.all(V[leaves & (edge > 1e-3)] == 0.0)


def test_hard_shadow_map_skips_transparent_texels(frames, texdir):
    """Measured (1024² cube faces): 17 of the 2990 floor pixels under the card (0.6 %) differ
    from exact visibility, all within 0.035 texel of a leaf-texture texel edge (the shadow map
    samples the texture's outline at its own texel centres); 99.6 % of the hole pixels are lit,
    98.6 % of the leaf pixels shadowed."""
    _, alpha = texdir
    frame, _ = frames(0.5)
    Vx, under, edge = exact_visibility(frame, alpha, 0.5)
    fl = floor_mask(frame)
    vis = frame.gbuffer.to_image(get("hard").render(frame, {}).visibility["p"])
    holes, leaves = fl & under & (Vx == 1), fl & under & (Vx == 0)
    assert np.mean(vis[holes] == 1.0) > 0.97   # light through the holes: the map skipped them
    assert np.mean(vis[leaves] == 0.0) > 0.97
    wrong = fl & (vis != Vx)
    assert wrong.sum() <= 0.01 * fl.sum()
    assert np.all(edge[wrong & under] < 0.1)  # at an outline (a shadow-map texel is ~0.07 texture texel)


def test_gbuffer_sees_the_floor_through_holes(frames, texdir):
    _, alpha = texdir
    frame, _ = frames(0.5)
    gb = frame.gbuffer
    o = np.stack([a.numpy() for a in (gb.rays.o.x, gb.rays.o.y, gb.rays.o.z)], 1).astype(np.float64)
    d = np.stack([a.numpy() for a in (gb.rays.d.x, gb.rays.d.y, gb.rays.d.z)], 1).astype(np.float64)
    t, u, v, inside = card_hit(o, d)
    opaque, edge = texel_lookup(alpha, u, v, 0.5)
    shp = (gb.height, gb.width)
    on_card = (inside & (t > 0)).reshape(shp)
    opaque, edge = opaque.reshape(shp), edge.reshape(shp)
    sid = gb.shape_id[..., 0]
    card, floor = frame.scene.shape_names.index("card"), frame.scene.shape_names.index("floor")
    clear = edge > 1e-3
    through = on_card & ~opaque & clear
    assert through.sum() > 300
    assert np.all(sid[through] == floor)                    # the floor behind a hole
    assert np.all(sid[on_card & opaque & clear] == card)
    # and the point seen there is the floor's (y = 0) at the camera ray's full distance
    p = np.stack([a.numpy() for a in (gb.p.x, gb.p.y, gb.p.z)], 1).reshape(*shp, 3)
    assert np.abs(p[through][:, 1]).max() < 1e-4
    t_floor = -o[:, 1] / d[:, 1]
    dist = np.linalg.norm((o + t_floor[:, None] * d) - np.asarray([0.0, 5.5, 2.0]), axis=1).reshape(shp)
    assert np.allclose(gb.view_depth[..., 0][through], dist[through], atol=1e-3)


def test_cutoff_changes_the_hole_set_as_the_thresholded_texture_predicts(frames, texdir):
    _, alpha = texdir
    holes = {}
    for cutoff in (0.25, 0.75):
        frame, V = frames(cutoff)
        Vx, under, edge = exact_visibility(frame, alpha, cutoff)
        fl = floor_mask(frame)
        wrong = fl & (V != Vx)
        assert np.all(edge[wrong] < 1e-3) and wrong.sum() <= 0.001 * fl.sum()
        holes[cutoff] = fl & under & (V == 1)
    # a higher cut-off discards more texels: every hole stays a hole and new ones open
    assert np.all(holes[0.75][holes[0.25]])
    assert (holes[0.75] & ~holes[0.25]).sum() > 100
    # the texture itself predicts the change: texels with 0.25 <= alpha < 0.75 exist
    a = alpha / 255.0
    assert np.count_nonzero((a >= 0.25) & (a < 0.75)) > 20


# ---------------------------------------------------------------------------------------------
# scene format

def test_missing_texture_and_bad_cutoff_name_the_key(texdir, tmp_path):
    d, _ = texdir
    with pytest.raises(SceneError, match=r"shapes\[1\]\.alpha_texture.*nothere\.png"):
        parse(scene_dict(texture="nothere.png"), str(d / "s.toml"))
    for bad in (1.5, -0.1, "half", True):
        with pytest.raises(SceneError, match=r"shapes\[1\]\.alpha_cutoff"):
            parse(scene_dict(cutoff=bad), str(d / "s.toml"))
    no_tex = scene_dict()
    del no_tex["shapes"][1]["alpha_texture"]
    with pytest.raises(SceneError, match=r"shapes\[1\]\.alpha_cutoff.*without alpha_texture"):
        parse(no_tex, str(d / "s.toml"))
    # a colour RGB image has no alpha: refused, naming the key (a grey one is read as a mask)
    import mitsuba as mi
    rgb = np.zeros((4, 4, 3), np.uint8)
    rgb[..., 1] = 200
    mi.Bitmap(rgb, pixel_format=mi.Bitmap.PixelFormat.RGB).write(str(tmp_path / "rgb.png"))
    with pytest.raises(SceneError, match=r"shapes\[1\]\.alpha_texture.*alpha"):
        parse(scene_dict(texture="rgb.png"), str(tmp_path / "s.toml"))
    (tmp_path / "junk.png").write_bytes(b"not an image")
    with pytest.raises(SceneError, match=r"shapes\[1\]\.alpha_texture"):
        parse(scene_dict(texture="junk.png"), str(tmp_path / "s.toml"))


def test_greyscale_mask_is_read_as_its_grey_value(tmp_path):
    import mitsuba as mi
    from shadowlab.scene.textures import read_alpha
    g = np.array([[0, 64], [128, 255]], np.uint8)
    mi.Bitmap(g, pixel_format=mi.Bitmap.PixelFormat.Y).write(str(tmp_path / "g.png"))
    assert np.allclose(read_alpha(tmp_path / "g.png"), g / 255.0, atol=1e-6)


def test_digest_unchanged_without_alpha_and_hashes_the_texture(texdir, tmp_path):
    # committed references store the hash of their scene: adding the keys must not change it
    refs = sorted(Path(__file__).resolve().parents[1].glob("references/*/*/meta.json"))
    for m in refs:
        meta = json.loads(m.read_text())
        spec = load_spec(resolve(meta["scene"]))
        if "frame" in meta:  # one frame of a camera path
            spec = spec.at_frame(meta["frame"])
        if not any(s.alpha_texture for s in spec.shapes):
            assert meta["scene_hash"] == spec.digest(), m
    # with a texture: its content and the cut-off are hashed, not its path
    d, alpha = texdir
    base = parse(scene_dict(), str(d / "s.toml")).digest()
    assert parse(scene_dict(cutoff=0.6), str(d / "s.toml")).digest() != base
    (tmp_path / "leaf.png").write_bytes((d / "leaf.png").read_bytes())
    assert parse(scene_dict(), str(tmp_path / "s.toml")).digest() == base
    write_leaf_png(tmp_path / "leaf.png", size=TEX + 1)
    assert parse(scene_dict(), str(tmp_path / "s.toml")).digest() != base


def test_builtin_leaf_texture_is_the_generators_output():
    import mitsuba as mi
    png = Path(__file__).resolve().parents[1] / "scenes" / "textures" / "leaf.png"
    a = np.array(mi.Bitmap(str(png)))[..., 3]
    assert np.array_equal(a, leaf_alpha())
    spec = load_spec(resolve("foliage"))
    assert any(s.alpha_texture for s in spec.shapes)
