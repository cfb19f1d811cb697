"""A flat-shaded UV sphere (PLY) over a floor under a spot light, shared by tests/test_pcf_acne.py
and tests/test_default_acne.py: the mesh on which shadow-map acne shows."""

import numpy as np

from scene_builder import floor, frame_from
from shadowlab.exchange.ply import write_ply
from shadowlab.scene.mesh import _sphere


def ball_frame(d, segments: int):
    """The FrameContext of the ball scene at 128², its mesh a UV sphere of ``segments`` written into ``d``."""
    P, _, _, F = _sphere(segments)
    write_ply(d / "ball.ply", (P * 0.6).astype(np.float32), np.zeros_like(P, np.float32),
              np.zeros((len(P), 2), np.float32), F.astype(np.int32))
    spec = {"name": "acne", "camera": {"position": [0, 3.5, 3.5], "target": [0, 0.5, 0], "fov": 40,
                                       "resolution": [128, 128]},
            "lights": [{"name": "L", "kind": "spot", "position": [1.5, 3.0, 1.0], "target": [0, 0.5, 0],
                        "angle": 35.0, "power": 100.0, "shadow_map": 1024}],
            "shapes": [floor(3.0), {"name": "ball", "type": "ply", "filename": "ball.ply", "translate": [0, 0.8, 0]}]}
    return frame_from(spec, d / "acne.toml")
