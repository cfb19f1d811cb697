"""Which techniques apply to a scene is decided once, from the scene spec, before any work (issue 27):
``techniques_for`` does not offer the SDF techniques for a scene of meshes, nor the shadow maps for
SDF-only objects; ``compare -t all`` runs what applies and names what it skipped and why; ``fit --all``
gives the same reason."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from scene_builder import floor, spec_of, write_scene
from shadowlab import techniques_for
from shadowlab.exchange.ply import write_ply
from shadowlab.scene.mesh import _sphere
from shadowlab.techniques import base as tbase

ROOT = Path(__file__).resolve().parents[1]
CAM = {"position": [0, 3.0, 3.5], "target": [0, 0.4, 0], "fov": 40, "resolution": [32, 32]}
SPHERE = {"name": "key", "kind": "sphere", "position": [1.0, 3.0, 1.0], "radius": 0.3, "power": 300.0}


def _mesh_scene(d: Path) -> Path:
    """A floor and a PLY ball under a sphere light, written into ``d``."""
    P, _, _, F = _sphere(12)
    write_ply(d / "ball.ply", (P * 0.5).astype(np.float32), np.zeros_like(P, np.float32),
              np.zeros((len(P), 2), np.float32), F.astype(np.int32))
    return write_scene(d / "meshy.toml", {"name": "meshy", "camera": CAM, "lights": [SPHERE], "shapes": [
        floor(2.0), {"name": "ball", "type": "ply", "filename": "ball.ply", "translate": [0, 0.6, 0]}]})


def _sdf_scene(d: Path) -> Path:
    """A floor (a rectangle, which has an SDF twin) and an SDF-only ball ([[sdf]]) under the same light."""
    return write_scene(d / "blobby.toml", {"name": "blobby", "camera": CAM, "lights": [SPHERE],
                                           "shapes": [floor(2.0)],
                                           "sdf": [{"name": "ball", "type": "sphere", "center": [0, 0.6, 0],
                                                    "radius": 0.5}]})


def _cli(*args, refs: Path):
    env = {**os.environ, "SHADOWLAB_REFERENCES": str(refs)}
    return subprocess.run([sys.executable, "-m", "shadowlab.cli", *args], capture_output=True, text=True, env=env,
                          cwd=ROOT, timeout=600)


SDF = [n for n in tbase.names() if n.startswith("sdf_")]
MAPS = ["hard", "pcf", "pcss", "vsm", "esm", "evsm", "msm"]


def test_techniques_for_a_mesh_scene_leaves_out_the_sdf_techniques(tmp_path):
    why = techniques_for(str(_mesh_scene(tmp_path)))
    assert SDF and all(why[n] and "'ball' is a ply mesh" in why[n] for n in SDF), {n: why[n] for n in SDF}
    assert all(why[n] is None for n in MAPS)


def test_techniques_for_an_sdf_only_scene_leaves_out_the_shadow_maps(tmp_path):
    why = techniques_for(str(_sdf_scene(tmp_path)))
    assert all(why[n] is None for n in SDF)
    assert all(why[n] and "SDF-only" in why[n] for n in MAPS)


@pytest.mark.parametrize("shape,reason", [
    ({"name": "leaf", "type": "rectangle", "alpha_texture": str(ROOT / "scenes" / "textures" / "leaf.png")},
     "alpha-tested"),
    ({"name": "pipe", "type": "cylinder", "caps": False}, "open cylinder"),
])
def test_shapes_without_an_sdf_twin_are_named(shape, reason):
    spec = spec_of({"name": "t", "camera": CAM, "lights": [SPHERE], "shapes": [floor(2.0), shape]})
    assert reason in tbase.get("sdf_hard").unsupported(spec)
    assert tbase.get("sdf_hard").unsupported(spec_of({"name": "t", "camera": CAM, "lights": [SPHERE],
                                                      "shapes": [floor(2.0)]})) is None


def test_compare_all_on_a_mesh_scene_runs_what_applies_and_says_what_it_skipped(tmp_path):
    scene, refs, out = _mesh_scene(tmp_path), tmp_path / "refs", tmp_path / "report"
    refs.mkdir()
    r = _cli("reference", str(scene), "--max-rounds", "2", "--spp", "0", refs=refs)
    assert r.returncode == 0, r.stderr
    r = _cli("compare", str(scene), "-t", "all", "-o", str(out), refs=refs)
    assert r.returncode == 0, r.stderr
    for n in SDF:
        assert f"skipping {n}: {n}: the scene has no signed distance field (shape 'ball' is a ply mesh" in r.stderr
    ran = set(json.loads((out / "metrics.json").read_text())["techniques"])
    assert ran == {n for n, w in techniques_for(str(scene)).items() if w is None and not tbase.get(n).external}
    assert "not in all: babylon:basic" in r.stderr                  # the engines run when named
    assert set(MAPS) <= ran and not ran & set(SDF)

    # fit --all skips the same techniques for the same reason
    r = _cli("fit", str(scene), "--all", "--method", "grid", "--grid-points", "2", "--rounds", "1",
             "-o", str(tmp_path / "fit"), refs=refs)
    assert r.returncode == 0, r.stderr
    skipped = json.loads((tmp_path / "fit" / "fit.json").read_text())["skipped"]
    assert {n: skipped[n] for n in SDF} == {n: techniques_for(str(scene))[n] for n in SDF}


def test_compare_all_on_an_sdf_scene_runs_the_sdf_techniques(tmp_path):
    scene, refs, out = _sdf_scene(tmp_path), tmp_path / "refs", tmp_path / "report"
    refs.mkdir()
    r = _cli("reference", str(scene), "--max-rounds", "2", "--spp", "0", refs=refs)
    assert r.returncode == 0, r.stderr
    r = _cli("compare", str(scene), "-t", "all", "-o", str(out), refs=refs)
    assert r.returncode == 0, r.stderr
    assert "skipping pcf: pcf: the scene has SDF-only objects" in r.stderr
    ran = set(json.loads((out / "metrics.json").read_text())["techniques"])
    assert ran == set(SDF)
