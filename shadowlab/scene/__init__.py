"""Scenes: the TOML format (spec), lights (emitters), the Mitsuba scene (build)."""

from .spec import SceneSpec, LightSpec, ShapeSpec, Camera, load_spec, resolve, builtin_names, parse
from .build import Scene, build, load

__all__ = ["SceneSpec", "LightSpec", "ShapeSpec", "Camera", "load_spec", "resolve", "builtin_names",
           "parse", "Scene", "build", "load"]
