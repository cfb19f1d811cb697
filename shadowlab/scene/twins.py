"""A scene's signed distance field: the SDF twins of its ``[[shapes]]`` plus its ``[[sdf]]`` objects.

Every Mitsuba primitive of a scene file (rectangle, disk, cube, sphere, capped cylinder) has a
twin in :mod:`shadowlab.sdf.field` (:func:`~shadowlab.sdf.field.twin_of`), built from the very
``to_world`` matrices Mitsuba loads (:func:`shadowlab.scene.build.shape_dicts`); the SDF-only
objects of the ``[[sdf]]`` tables (:mod:`shadowlab.scene.sdf_spec`) join them. So one scene file
gives the Mitsuba scene (the ground truth of a ``"mitsuba"`` scene) and its SDF
[Bán 2019, §2.4–2.6].
"""

from __future__ import annotations

import numpy as np

from ..sdf.field import SDF, Union, twin_of
from .build import shape_dicts
from .sdf_spec import build_objects


#: the ``[[shapes]]`` types with an SDF twin (:func:`shadowlab.sdf.field.twin_of`); any other type (a mesh) has none
TWIN_TYPES = ("rectangle", "disk", "cube", "sphere", "cylinder")


def why_no_twin(shape_spec) -> str | None:
    """Why one ``[[shapes]]`` entry has no SDF twin, None when it has one: meshes (any type but
    :data:`TWIN_TYPES`), alpha-tested shapes (their holes are not a solid) and open cylinders
    (``caps = false``). Read from the spec alone, so applicability is decided before any work."""
    s = shape_spec
    if s.type not in TWIN_TYPES:
        return f"shape {s.name!r} is a {s.type} mesh"
    if s.alpha_tested:
        return f"shape {s.name!r} is alpha-tested"
    if s.type == "cylinder" and not s.caps:
        return f"shape {s.name!r} is an open cylinder (caps = false)"
    return None


def why_no_sdf(spec) -> str | None:
    """Why a scene spec has no signed distance field of what casts shadows (:func:`sdf_of_spec`
    would give None), None when it has one; from the spec alone, nothing is built. A shape that
    casts no shadow (``casts_shadows = false``) needs no twin; a light whose panel casts would
    (its panel is not in the SDF)."""
    casting = [s for s in spec.shapes if s.casts_shadows]
    for s in casting:
        if why := why_no_twin(s):
            return why
    if lit := [l.name for l in spec.lights if l.casts_shadows]:
        return f"the panel of light {lit[0]!r} casts shadows (casts_shadows = true) and has no SDF twin"
    if not casting and not getattr(spec, "sdf", ()):
        return "no shape casts shadows"
    return None


def twin_of_shape(shape_spec) -> SDF | None:
    """SDF twin of one ``[[shapes]]`` entry, built from the same Mitsuba dicts the scene loads
    (:func:`shadowlab.scene.build.shape_dicts`), or None when it has none (:func:`why_no_twin`)."""
    s = shape_spec
    if why_no_twin(s):
        return None
    d = shape_dicts(s)[s.name]
    M = np.array(d["to_world"].matrix, dtype=np.float64)
    return twin_of(d["type"], M).named(s.name, s.albedo)


def sdf_of_spec(spec) -> SDF | None:
    """The SDF of a scene spec: Mitsuba twins of its ``[[shapes]]`` that cast shadows and its ``[[sdf]]``
    objects, united; None if some such shape has no twin (meshes, alpha-tested or open shapes)."""
    if why_no_sdf(spec):
        return None
    parts = [twin_of_shape(s) for s in spec.shapes if s.casts_shadows] + list(build_objects(getattr(spec, "sdf", ())))
    return Union(*parts)


def sdf_of(scene) -> SDF | None:
    """SDF of a loaded Scene (:mod:`shadowlab.scene.build`), None if it has meshes or no SDF.
    Built once per Scene and kept on it."""
    cached = scene.__dict__.get("_sdf", False)
    if cached is False:
        cached = sdf_of_spec(scene.spec)
        scene.__dict__["_sdf"] = cached
    return cached
