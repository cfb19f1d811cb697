"""A small scene with one light of every kind, shared by tests/test_lightview_fits.py and the
script that saved tests/data/lightview_baseline.npz (the light maps before per-map fits existed).
The two area lights' panels cast shadows (``casts_shadows = true``), as every panel did when the
baseline was saved, so the maps and the shadow rays the tests compare them with see them."""

SHAPES = [
    {"name": "floor", "type": "rectangle", "rotate": [[0, 0, 1, 0.05], [1, 0, 0, -90]], "scale": 3.0},
    {"name": "box", "type": "cube", "translate": [-0.7, 0.4, -0.2], "rotate": [0, 1, 0, 30], "scale": 0.4},
    {"name": "ball", "type": "sphere", "center": [0.7, 0.6, -0.1], "radius": 0.45},
]
CAMERA = {"position": [0.0, 4.5, 4.5], "target": [0.0, 0.0, 0.3], "fov": 50, "resolution": [64, 48]}
LIGHTS = [
    {"name": "spot", "kind": "spot", "position": [-0.4, 3.0, -2.0], "target": [0.1, 0.0, 0.6], "angle": 35.0,
     "power": 100.0},
    {"name": "sun", "kind": "directional", "direction": [0.3, -1.0, 0.8], "irradiance": 3.0},
    {"name": "bulb", "kind": "sphere", "position": [0.3, 2.5, 0.5], "radius": 0.2, "power": 100.0,
     "casts_shadows": True},
    {"name": "panel", "kind": "rect", "position": [1.0, 3.0, 1.0], "target": [0.0, 0.0, 0.0], "size": [0.5, 0.5],
     "power": 100.0, "casts_shadows": True},
]
SCENE = {"name": "lightview", "camera": CAMERA, "lights": LIGHTS, "shapes": SHAPES}
