"""Steel structures the robot inspects, built from parametric members
(:mod:`robot_link.sim.members`), each type with its dimensions drawn from a seed.

World frame as in :mod:`robot_link.sim.structure`: the robot drives on the surface z = 0
from the z < 0 side (its magnets hold it to any steel face: a flange, a web, a chord's
side, a gusset plate), x along the member it drives on, metres. The structure around
that face is what the ToF camera sees.

=================  =========================================================================
``i_girder``       deck plate beside an I-girder with transverse stiffeners and bolts
``box_girder``     inside a box girder on its bottom flange: inclined webs, longitudinal
                   stiffeners, top flange with shear studs, a bolted web splice, X-braced
                   internal cross-frames of angles on connection plates
``cross_frames``   under a deck between two I-girders, X-braced (skewed) cross-frames of
                   angles with struts, bolted to connection plates
``truss``          on the side face of a truss's bottom chord: gusset plates with bolt
                   groups at the panel points, verticals and diagonals framing into them
``gusset_joint``   on a large gusset plate: bolt groups, angle members bolted on it in
                   several directions, the chord beside it
=================  =========================================================================
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from robot_link.sim.members import angle, bolts, box, grid, plate, wide_flange

X, Y, Z = np.eye(3)
UP = -Z  # away from the face the robot drives on


@dataclass
class Scene:
    """A structure's mesh and where on its face z = 0 the robot can drive lanes along x."""

    kind: str
    mesh: o3d.geometry.TriangleMesh = field(repr=False)
    lanes_y_m: tuple[float, float]  # the two lanes' y
    x_range_m: tuple[float, float]  # where the lanes run


def _frames_x(rng: np.random.Generator, x0: float, x1: float, spacing: float) -> np.ndarray:
    """Positions of repeating members (cross-frames, panel points) from a random phase."""
    return np.arange(x0 + rng.uniform(0, spacing), x1, spacing)


def i_girder(rng: np.random.Generator) -> Scene:
    """The deck plate beside an I-girder (:func:`robot_link.sim.structure.girder_geometry`)."""
    from robot_link.sim.structure import girder_geometry

    plate_h = rng.uniform(0.85, 1.0)
    mesh = girder_geometry(1.6, plate_h, 1.6, rng.uniform(0.4, 0.7))
    return Scene("i_girder", mesh, (plate_h - 0.34, plate_h - 0.16), (0.5, 1.2))


def box_girder(rng: np.random.Generator) -> Scene:
    """Inside a box girder, on the bottom flange between its two (inclined) webs."""
    width, depth = rng.uniform(1.0, 1.4), rng.uniform(0.8, 1.2)
    tilt = np.radians(rng.uniform(0, 12))  # webs lean outwards going up
    x0, x1 = -2.0, 3.5
    length = x1 - x0
    xm = (x0 + x1) / 2
    mesh = box(x0, x1, -0.05, width + 0.05, 0, 0.016)  # bottom flange
    top_y = (-depth * np.tan(tilt), width + depth * np.tan(tilt))
    for side, y_bottom in ((1, 0.0), (-1, width)):
        up = np.array([0, -side * np.sin(tilt), -np.cos(tilt)])  # along the web, upwards
        inward = np.array([0, side * np.cos(tilt), -side * np.sin(tilt)])
        base = np.array([xm, y_bottom, 0.0])
        height = depth / np.cos(tilt)
        mesh += plate(base + up * height / 2 - inward * 0.007, inward, X, (length, height), 0.014)
        stiff = base + up * height * rng.uniform(0.4, 0.6) + inward * 0.06
        mesh += plate(stiff, up, X, (length, 0.12), 0.014)  # longitudinal stiffener
        xs = rng.uniform(0.1, 1.0)  # bolted web splice
        splice = base + up * height * 0.45 + inward * 0.008 + X * (xs - xm)
        mesh += plate(splice, inward, X, (0.5, height * 0.7), 0.016)
        corner = splice - X * 0.2 - up * height * 0.3 + inward * 0.008
        mesh += bolts(grid(corner, X, up, 4, 6, (0.08, height * 0.12)), inward)
    mesh += box(x0, x1, top_y[0] - 0.2, top_y[1] + 0.2, -depth - 0.025, -depth)  # top flange
    studs = [
        (sx, y, -depth - 0.025)
        for sx in np.arange(x0, x1, 0.25)
        for y in np.linspace(top_y[0], top_y[1], 3)
    ]
    mesh += bolts(studs, UP, radius=0.011, height=0.1)
    skew = np.radians(rng.uniform(-15, 15))
    for xc in _frames_x(rng, x0 + 0.3, x1 - 0.3, rng.uniform(0.65, 0.85)):
        ends = []
        for side, y_bottom in ((1, 0.0), (-1, width)):
            up = np.array([0, -side * np.sin(tilt), -np.cos(tilt)])
            inward = np.array([0, side * np.cos(tilt), -side * np.sin(tilt)])
            x_here = xc + y_bottom * np.tan(skew)
            base = np.array([x_here, y_bottom, 0.0])
            height = depth / np.cos(tilt)
            mesh += plate(
                base + up * height * 0.5 + inward * 0.075, X, up, (height * 0.9, 0.15), 0.012
            )
            low, high = base + up * 0.28 + inward * 0.14, base + up * (height - 0.1) + inward * 0.14
            mesh += bolts([low + inward * -0.06 + up * 0.05, high - up * 0.05 - inward * 0.06], X)
            ends.append((low, high))
        (l0, h0), (l1, h1) = ends
        legs = (0.075, 0.075)
        mesh += angle(l0, h1, legs, 0.008, X) + angle(h0, l1, legs, 0.008, X)
        mesh += angle(h0, h1, legs, 0.008, Z)  # top strut
    lane = rng.uniform(0.25, 0.4) * width
    return Scene("box_girder", mesh, (lane, lane + rng.uniform(0.18, 0.26)), (0.1, 0.8))


def cross_frames(rng: np.random.Generator) -> Scene:
    """Under a deck between two I-girders joined by X-braced cross-frames."""
    spacing, depth = rng.uniform(1.2, 1.8), rng.uniform(0.7, 1.1)
    x0, x1 = -2.0, 3.5
    mesh = box(x0, x1, -0.5, spacing + 0.5, 0, 0.2)  # the deck's underside is z = 0
    for y in (0.0, spacing):
        mesh += box(x0, x1, y - 0.15, y + 0.15, -0.02, 0)  # top flange
        mesh += box(x0, x1, y - 0.007, y + 0.007, -depth + 0.025, -0.02)  # web
        mesh += box(x0, x1, y - 0.16, y + 0.16, -depth, -depth + 0.025)  # bottom flange
    skew = np.radians(rng.uniform(-20, 20))
    top, bottom = -0.3, -depth + 0.09  # the robot passes beneath the top strut
    for xc in _frames_x(rng, x0 + 0.3, x1 - 0.3, rng.uniform(0.65, 0.85)):
        xf = xc + spacing * np.tan(skew)
        for x, y, inward in ((xc, 0.0, 1), (xf, spacing, -1)):
            mesh += box(
                x - 0.006, x + 0.006, y + inward * 0.007, y + inward * 0.14, -depth + 0.03, -0.03
            )
            centre = (x, y + inward * 0.1, 0.0)
            mesh += bolts(
                [np.add(centre, (0.006, 0, z)) for z in (top, top - 0.08, bottom + 0.08, bottom)], X
            )
        a, b = np.array([xc, 0.12, top]), np.array([xf, spacing - 0.12, bottom])
        c, d = np.array([xc, 0.12, bottom]), np.array([xf, spacing - 0.12, top])
        legs = (0.09, 0.09)
        mesh += angle(a, b, legs, 0.009, X) + angle(c, d, legs, 0.009, X)
        mesh += angle(c, b, legs, 0.009, Z)  # bottom strut
        mesh += angle(a, d, legs, 0.009, Z)  # top strut
    lane = rng.uniform(0.2, 0.4)
    return Scene("cross_frames", mesh, (lane, lane + rng.uniform(0.18, 0.26)), (0.1, 0.8))


def truss(rng: np.random.Generator) -> Scene:
    """On the outer side face of a truss's bottom chord (a box section), gussets at the
    panel points with bolt groups, verticals and diagonals framing into them."""
    chord_h, panel = rng.uniform(0.5, 0.65), rng.uniform(0.9, 1.3)
    height = rng.uniform(1.5, 2.2)
    x0, x1 = -2.5, 4.0
    mesh = box(x0, x1, 0, chord_h, 0, 0.4)  # chord web: the face the robot drives on
    for y in (-0.016, chord_h):
        mesh += box(x0, x1, y, y + 0.016, -0.05, 0.45)  # cover plates, wider than the webs
    top = chord_h + height
    mesh += box(x0, x1, top, top + 0.4, 0, 0.4)  # top chord
    points = _frames_x(rng, x0 + 0.5, x1 - 0.5, panel)
    direction = 1 if rng.uniform() < 0.5 else -1
    for k, xp in enumerate(points):
        mesh += box(xp - 0.4, xp + 0.4, -0.05, chord_h + 0.55, -0.014, 0)  # gusset plate
        mesh += bolts(grid((xp - 0.3, 0.08, -0.014), X, Y, 5, 3, (0.15, 0.12)), UP)
        mesh += wide_flange((xp, chord_h + 0.1, 0.2), (xp, top, 0.2), 0.3, 0.3, 0.012, 0.018, X)
        mesh += bolts(grid((xp - 0.09, chord_h + 0.12, -0.014), X, Y, 2, 3, (0.18, 0.12)), UP)
        end = np.array([xp + direction * panel * (1 if k % 2 else -1), top, -0.014])
        start = np.array([xp, chord_h + 0.2, -0.014])
        mesh += angle(start, end, (0.1, 0.1), 0.011, UP)
    lane = rng.uniform(0.1, 0.16)
    return Scene("truss", mesh, (lane, lane + rng.uniform(0.18, chord_h - 0.1 - lane)), (0.1, 0.8))


def gusset_joint(rng: np.random.Generator) -> Scene:
    """On a large gusset plate: bolt groups and angle members bolted on it, the chord
    beside it."""
    w, h = rng.uniform(2.4, 3.0), rng.uniform(1.2, 1.6)
    x0 = -0.7
    mesh = box(x0, x0 + w, -0.1, h, 0, 0.016)  # the plate
    mesh += box(x0 - 2, x0 + w + 2, -0.6, -0.1, -0.25, 0.3)  # the chord beside it
    for k, xb in enumerate(np.arange(x0 + 0.25, x0 + w - 0.2, rng.uniform(0.4, 0.6))):
        rows = 3 if k % 2 else 2
        mesh += bolts(grid((xb, 0.05, 0), X, Y, 3, rows, (0.08, 0.09)), UP)  # chord splice bolts
    for k, theta in enumerate(rng.uniform(35, 65, 3) * np.array([1, -1, 1])):
        foot = np.array([x0 + (k + 0.5) * w / 3, h - 0.15, 0])
        d = np.array(
            [np.cos(np.radians(theta)) * np.sign(theta), np.sin(np.radians(abs(theta))), 0]
        )
        mesh += angle(foot, foot + d * 2.0, (0.1, 0.1), 0.012, UP)  # leg standing out of the plate
        mesh += bolts([foot + d * s + np.cross(Z, d) * 0.05 for s in (0.1, 0.2, 0.3)], UP)
    lane = rng.uniform(0.3, 0.4)
    return Scene("gusset_joint", mesh, (lane, lane + rng.uniform(0.18, 0.26)), (0.1, 0.8))


SCENES: dict[str, Callable[[np.random.Generator], Scene]] = {
    "i_girder": i_girder,
    "box_girder": box_girder,
    "cross_frames": cross_frames,
    "truss": truss,
    "gusset_joint": gusset_joint,
}


def make_scene(kind: str, seed: int) -> Scene:
    """The structure of type ``kind`` (a key of :data:`SCENES`) with dimensions from ``seed``."""
    if kind not in SCENES:
        raise ValueError(f"unknown structure {kind!r}; one of {', '.join(SCENES)}")
    scene = SCENES[kind](np.random.default_rng(seed))
    scene.mesh.compute_vertex_normals()
    return scene
