"""Signed distance fields: representation, scene twins, tracing, G-buffer (004_15e39f1e68ecd753.txt).

* :mod:`.field` — SDF primitives, transforms, CSG, offset, Mandelbulb (004 §2.4–2.6);
  :func:`sdf_of` gives a loaded scene's SDF (twins of its Mitsuba primitives + ``[[sdf]]`` objects).
* :mod:`.spec` — the ``[[sdf]]`` tables of scene files (SDF-only objects).
* :mod:`.trace` — sphere tracing, cone tracing, hard visibility (004 §2.7–2.9, §3.1).
* :mod:`.gbuffer` — the cone-traced G-buffer of scenes with SDF-only content (004 §2.9).
* :mod:`.reference` — the ground truth of such scenes (the Monte-Carlo cone reference, 004 §3.3.1),
  :func:`reference_hook`.
* ``soft``, ``shading``, ``bench`` — soft-shadow algorithms and techniques (004 §4–5).
"""

from .field import (SDF, Box, Capsule, Cylinder, Difference, Intersection, Mandelbulb, Offset, Plane, Segment,
                    Sphere, Transformed, Union, sdf_of, transform)
from .trace import cone_trace, hard_visibility, sphere_trace


def reference_hook(frame, **kw):
    """Ground truth of a scene with SDF-only content (``shadowlab reference`` calls this instead of
    Mitsuba): :func:`shadowlab.sdf.reference.render_truth`."""
    from .reference import render_truth
    return render_truth(frame, **kw)


__all__ = ["SDF", "Box", "Capsule", "Cylinder", "Difference", "Intersection", "Mandelbulb", "Offset", "Plane",
           "Segment", "Sphere", "Transformed", "Union", "sdf_of", "transform",
           "cone_trace", "hard_visibility", "sphere_trace", "reference_hook"]
