"""Signed distance fields: a geometry library [Bán 2019].

It imports nothing else of shadowlab (only numpy, Dr.Jit and Mitsuba; bad arguments raise
ValueError / TypeError, which callers turn into shadowlab's errors):

* :mod:`.field` — SDF primitives, transforms, CSG, offset, Mandelbulb [Bán 2019, §2.4–2.6], and
  the twins of Mitsuba's canonical primitives (:func:`~.field.twin_of`);
* :mod:`.trace` — sphere tracing, cone tracing, hard visibility [Bán 2019, §2.7–2.9, §3.1];
* :mod:`.soft` — the cone maths (τ, τ⁻¹, cones between spheres), the single-ray soft-shadow
  marches, the Quílez / Aaltonen baseline and the Monte-Carlo cone visibility [Bán 2019, ch. 3–4].

What needs a scene lives elsewhere: a scene's SDF and its ``[[sdf]]`` tables in
:mod:`shadowlab.scene.twins` and :mod:`shadowlab.scene.sdf_spec`, the cone-traced G-buffer in
:mod:`shadowlab.render.sdf_gbuffer`, the Monte-Carlo cone truth in
:mod:`shadowlab.reference.sdf_truth`, the techniques in :mod:`shadowlab.techniques.sdf_shadows`.
"""

from .field import (SDF, Box, Capsule, Cylinder, Difference, Intersection, Mandelbulb, Offset, Plane, Segment, Sphere,
                    Transformed, Union, transform, twin_of)
from .trace import cone_trace, hard_visibility, sphere_trace

__all__ = ["SDF", "Box", "Capsule", "Cylinder", "Difference", "Intersection", "Mandelbulb", "Offset", "Plane",
           "Segment", "Sphere", "Transformed", "Union", "transform", "twin_of",
           "cone_trace", "hard_visibility", "sphere_trace"]
