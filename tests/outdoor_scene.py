"""A small outdoor scene for the directional-light families (csm, vtsm, fvsm): a floor, boxes and
poles from 2 m to 40 m, a sun with a small angular size."""

SHAPES = [
    {"name": "floor", "type": "rectangle", "rotate": [1, 0, 0, -90], "scale": 50.0},
    {"name": "box1", "type": "cube", "translate": [-1.5, 0.5, -4.0], "scale": 0.5},
    {"name": "box2", "type": "cube", "translate": [2.0, 1.0, -15.0], "scale": 1.0},
    {"name": "box3", "type": "cube", "translate": [-4.0, 2.0, -40.0], "scale": 2.0},
    {"name": "pole1", "type": "cylinder", "p0": [1.0, 0.0, -8.0], "p1": [1.0, 3.0, -8.0], "radius": 0.1},
    {"name": "pole2", "type": "cylinder", "p0": [-2.0, 0.0, -25.0], "p1": [-2.0, 5.0, -25.0], "radius": 0.2},
]
CAMERA = {"position": [0.0, 1.7, 2.0], "target": [0.0, 1.0, -20.0], "fov": 60, "resolution": [48, 32],
          "near": 0.1, "far": 150.0}
SUN = {"name": "sun", "kind": "directional", "direction": [0.4, -1.0, -0.3], "irradiance": 3.0,
       "angular_diameter": 0.53, "shadow_map": 256}
OUTDOOR = {"name": "outdoor", "camera": CAMERA, "lights": [SUN], "shapes": SHAPES}
