"""Closed forms the ground truth is checked against (tests/test_truth.py).

* :func:`cap_intersection` — solid angle of the intersection of two spherical caps
  (Mazonka 2012, "Solid angle of conical surfaces, polyhedral cones, and intersecting
  spherical caps", eq. 36): a spherical light partly hidden by a sphere occluder.
* :func:`sphere_visible_fraction` — visible solid-angle fraction of a spherical light seen
  from x past a sphere occluder.
* :func:`parallel_planes_fraction` — visible area fraction of a rectangular light over a
  parallel half-plane occluder, piecewise linear in the receiver position.
"""

from __future__ import annotations

import numpy as np


def cap_solid_angle(alpha):
    """Solid angle of a cap of half-angle ``alpha``: 2π(1 − cos α).

    >>> round(float(cap_solid_angle(np.pi / 2)), 6)  # a hemisphere
    6.283185
    """
    return 2.0 * np.pi * (1.0 - np.cos(alpha))


def cap_intersection(a1, a2, gamma):
    """Solid angle shared by caps of half-angles ``a1``, ``a2`` whose axes are ``gamma`` apart
    (all radians, arrays broadcast; half-angles < π/2).

    >>> float(cap_intersection(0.1, 0.2, 0.5))  # disjoint
    0.0
    >>> bool(np.isclose(cap_intersection(0.1, 0.3, 0.0), cap_solid_angle(0.1)))  # nested
    True
    """
    a1, a2, g = np.broadcast_arrays(np.asarray(a1, float), np.asarray(a2, float), np.asarray(gamma, float))
    out = np.zeros(a1.shape)
    disjoint = g >= a1 + a2
    nested = g <= np.abs(a1 - a2)
    part = ~disjoint & ~nested
    out[nested] = cap_solid_angle(np.minimum(a1, a2)[nested])
    if part.any():
        x1, x2, y = a1[part], a2[part], g[part]
        c1, c2, cg = np.cos(x1), np.cos(x2), np.cos(y)
        s1, s2, sg = np.sin(x1), np.sin(x2), np.sin(y)
        t0 = np.arccos(np.clip((cg - c1 * c2) / (s1 * s2), -1, 1))
        t1 = np.arccos(np.clip((c2 - cg * c1) / (sg * s1), -1, 1))
        t2 = np.arccos(np.clip((c1 - cg * c2) / (sg * s2), -1, 1))
        out[part] = 2.0 * (np.pi - t0 - t1 * c1 - t2 * c2)
    return out


def sphere_visible_fraction(x, light_c, light_r, occ_c, occ_r):
    """Visible fraction of the solid angle of a spherical light (centre ``light_c``, radius
    ``light_r``) seen from points ``x`` (N, 3), with a sphere occluder in between.
    Assumes the occluder, where it overlaps the light's cone, is nearer than the light."""
    x = np.atleast_2d(np.asarray(x, float))
    dl = np.asarray(light_c, float) - x
    do = np.asarray(occ_c, float) - x
    Ll, Lo = np.linalg.norm(dl, axis=1), np.linalg.norm(do, axis=1)
    al = np.arcsin(np.clip(light_r / Ll, 0, 1))
    ao = np.arcsin(np.clip(occ_r / Lo, 0, 1))
    g = np.arccos(np.clip(np.einsum("ij,ij->i", dl, do) / (Ll * Lo), -1, 1))
    return 1.0 - cap_intersection(al, ao, g) / cap_solid_angle(al)


def parallel_planes_fraction(xr, light_height, occ_height, light_width, edge_x=0.0):
    """Visible area fraction of a light spanning x ∈ [−w/2, w/2] at height H, over a
    half-plane occluder x < edge_x at height h < H, seen from receivers at (xr, 0).

    A light point x_l is hidden iff the segment to it crosses height h left of the edge:
    x_l < xr + (edge_x − xr)·H/h. The fraction is linear in xr across the penumbra.

    >>> float(parallel_planes_fraction(0.0, 4.0, 2.0, 1.0))  # under the edge: half the light
    0.5
    """
    xr = np.asarray(xr, float)
    cut = xr + (edge_x - xr) * light_height / occ_height
    return np.clip((light_width / 2 - cut) / light_width, 0.0, 1.0)
