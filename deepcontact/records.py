"""Record layouts shared by the engine, the data files, the wire and the server.

These mirror the patched Box2D's export structs byte for byte (b2DCBody,
b2DCContactPoint in box2d/deepcontact.patch); `simclient.engine` checks the
sizes against the compiled library at import. This module needs no Box2D, so
the server can use it.
"""

import numpy as np

BODY_DTYPE = np.dtype(
    [
        ("index", "<i4"),  # creation order, 0-based
        ("type", "<i4"),  # 0 static, 1 kinematic, 2 dynamic
        ("position", "<f4", (2,)),  # centre of mass (m): the body origin of circles and centred boxes
        ("angle", "<f4"),  # (rad)
        ("velocity", "<f4", (2,)),  # linear velocity (m/s)
        ("angular_velocity", "<f4"),  # (rad/s)
        ("mass", "<f4"),  # (kg), 0 for static bodies
        ("inertia", "<f4"),  # about the centre of mass (kg m^2)
        ("shape", "<i4"),  # 0 circle, 1 edge, 2 polygon, 3 chain; -1 several
        ("radius", "<f4"),  # bounding radius about the origin (m)
    ]
)
"""One body as the patch exports it (48 bytes, b2DCBody)."""

CONTACT_DTYPE = np.dtype(
    [
        ("key", "<u8"),  # equal on every step for the same contact point
        ("body_a", "<i4"),  # body indices (creation order)
        ("body_b", "<i4"),
        ("point", "<f4", (2,)),  # world point at collide time (m)
        ("normal", "<f4", (2,)),  # world normal from A to B
        ("separation", "<f4"),  # (m), negative when overlapping
        ("builtin", "<f4", (2,)),  # previous step's impulse (normal, tangent) (N s)
        ("warm_start", "<f4", (2,)),  # where the solver started; NaN until solved
        ("impulse", "<f4", (2,)),  # final impulse; NaN until solved
        ("friction", "<f4"),  # the contact's friction coefficient at collide time (sqrt(f_A f_B) of its fixtures)
    ]
)
"""One contact point as the patch exports it (64 bytes, b2DCContactPoint)."""
