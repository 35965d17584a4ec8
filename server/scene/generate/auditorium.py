"""Funkhouser & Séquin's test scene: an auditorium of ~440 detailed chairs, and their test path.

The paper's auditorium held 87,565 polygons, most of them in hundreds of copies
of one chair; drawn in full it took 0.43 s per frame against a 0.1 s target.
This one has a hall (floor, raked seating tiers, walls, ceiling, stage),
a few props on the stage, and 20 rows × 22 chairs of one ~250-triangle chair
— separate parts (legs, seat, slatted curved back, armrests), so quadric
decimation takes it through four halvings before it falls apart — about
110k triangles in all.

The tour passes the paper's three viewpoints: **A** at the front rows, looking
across many large, complex chairs; **B** in a stage corner looking up at bare
wall and ceiling (few, small objects); **C** in the middle of the seating,
spinning a full turn in 2 s so many chairs come into view at once.

World axes: z up, metres; the stage is at low y, the audience faces −y.
"""

from __future__ import annotations

import math

import numpy as np
import trimesh

from server.scene.generate.camera import looping_tour
from server.scene.source import Mesh, SourceObject, SourceScene

__all__ = ["auditorium", "chair_mesh", "ROWS", "SEATS_PER_ROW"]

ROWS = 20
SEATS_PER_ROW = 22  #: two blocks of 11 either side of the central aisle
ROW_PITCH = 0.95  #: metres between rows
RISER = 0.16  #: height of each seating tier above the one in front
SEAT_PITCH = 0.6  #: metres between chair centres in a row
FIRST_ROW_Y = 9.0
AISLE = 1.4  #: width of the central aisle
HALL_X = 15.0  #: the hall spans x ∈ [−HALL_X, HALL_X]
HALL_Y = (-2.0, 34.0)
HALL_Z = 11.0
STAGE_Y = 6.0  #: the stage front edge
STAGE_Z = 1.0


def _box(ext, at, transform=None) -> trimesh.Trimesh:
    m = trimesh.creation.box(ext)
    if transform is not None:
        m.apply_transform(transform)
    m.apply_translation(at)
    return m


def chair_mesh() -> Mesh:
    """The chair model (248 triangles), seat front toward −y, feet at z = 0, centred on x = y = 0.

    Parts stay separate closed meshes; slats follow an arc and the seat's front
    edge rolls down, so levels of detail have curvature to lose.
    """
    rot = trimesh.transformations.rotation_matrix
    parts = []
    for sx in (-0.21, 0.21):
        for sy in (-0.19, 0.19):
            leg = trimesh.creation.cylinder(radius=0.018, height=0.42, sections=5)
            leg.apply_translation((sx, sy, 0.21))
            parts.append(leg)
    seat = trimesh.creation.box((0.5, 0.46, 0.06)).subdivide()
    v = seat.vertices.copy()
    v[:, 2] -= 0.03 * np.clip((-v[:, 1] - 0.1) / 0.13, 0.0, 1.0)  # waterfall front edge
    seat = trimesh.Trimesh(v + (0.0, 0.0, 0.45), seat.faces, process=False)
    parts.append(seat)
    tilt = rot(-0.12, [1, 0, 0])
    for x in np.linspace(-0.16, 0.16, 5):  # curved slatted back
        ang = x / 0.6
        parts.append(_box((0.05, 0.018, 0.42), (x, 0.22 + 0.6 * (1 - math.cos(ang)), 0.72), rot(-ang, [0, 0, 1]) @ tilt))
    for sx in (-0.23, 0.23):
        parts.append(_box((0.04, 0.04, 0.55), (sx, 0.23, 0.72), tilt))
    parts.append(_box((0.5, 0.05, 0.06), (0.0, 0.26, 0.97), tilt))
    for sx in (-0.27, 0.27):
        parts.append(_box((0.06, 0.44, 0.04), (sx, 0.0, 0.66)))
    m = trimesh.util.concatenate(parts)
    return Mesh(np.asarray(m.vertices), np.asarray(m.faces))


def _hall() -> list[SourceObject]:
    """Floor, seating tiers, walls, ceiling and stage, each one closed box."""
    y0, y1 = HALL_Y
    w, t = HALL_X, 0.3
    boxes = {
        "floor": ((-w, y0, -0.2), (w, y1, 0.0)),
        "ceiling": ((-w, y0, HALL_Z), (w, y1, HALL_Z + t)),
        "wall_left": ((-w - t, y0, 0.0), (-w, y1, HALL_Z)),
        "wall_right": ((w, y0, 0.0), (w + t, y1, HALL_Z)),
        "wall_front": ((-w, y0 - t, 0.0), (w, y0, HALL_Z)),
        "wall_back": ((-w, y1, 0.0), (w, y1 + t, HALL_Z)),
        "stage": ((-w + 3.0, y0, 0.0), (w - 3.0, STAGE_Y, STAGE_Z)),
    }
    for r in range(1, ROWS):
        y = FIRST_ROW_Y + r * ROW_PITCH
        boxes[f"tier_{r:02d}"] = ((-w, y - ROW_PITCH / 2, 0.0), (w, y + ROW_PITCH / 2, r * RISER))
    out = []
    for name, (lo, hi) in boxes.items():
        lo, hi = np.array(lo), np.array(hi)
        m = _box(hi - lo, (lo + hi) / 2)
        out.append(SourceObject(name, "hall", [Mesh(np.asarray(m.vertices), np.asarray(m.faces))]))
    return out


def _props() -> list[SourceObject]:
    """A lectern, a grand piano, two speaker stacks and music stands on the stage."""
    z = STAGE_Z
    rot = trimesh.transformations.rotation_matrix
    props: dict[str, list[trimesh.Trimesh]] = {}
    props["lectern"] = [_box((0.6, 0.45, 1.05), (3.5, 3.0, z + 0.525)),
                        _box((0.7, 0.55, 0.05), (3.5, 3.0, z + 1.1), rot(0.3, [1, 0, 0]))]
    body = trimesh.creation.cylinder(radius=0.8, height=0.3, sections=24)
    body.apply_scale((1.0, 1.4, 1.0))
    body.apply_translation((-3.0, 2.2, z + 0.85))
    lid = _box((1.4, 1.9, 0.03), (-3.0, 2.2, z + 1.35), rot(-0.5, [0, 1, 0]))
    piano = [body, lid, _box((1.5, 0.5, 0.12), (-3.0, 0.75, z + 0.72))]
    for x, y in ((-3.6, 1.2), (-2.4, 1.2), (-3.0, 3.2)):
        leg = trimesh.creation.cylinder(radius=0.05, height=0.7, sections=8)
        leg.apply_translation((x, y, z + 0.35))
        piano.append(leg)
    props["piano"] = piano
    for i, x in enumerate((-10.0, 10.0)):
        props[f"speaker_{i}"] = [_box((0.8, 0.6, 1.2), (x, 4.5, z + 0.6)), _box((0.7, 0.55, 0.9), (x, 4.5, z + 1.65))]
    for i, x in enumerate(np.linspace(-1.5, 1.5, 4)):
        post = trimesh.creation.cylinder(radius=0.015, height=1.1, sections=6)
        post.apply_translation((x, 1.5, z + 0.55))
        props[f"stand_{i}"] = [post, _box((0.5, 0.02, 0.35), (x, 1.5, z + 1.2), rot(0.35, [1, 0, 0]))]
    out = []
    for name, parts in props.items():
        m = trimesh.util.concatenate(parts)
        out.append(SourceObject(name, "prop", [Mesh(np.asarray(m.vertices), np.asarray(m.faces))]))
    return out


def _chairs(rng: np.random.Generator) -> list[SourceObject]:
    model = chair_mesh()
    half = SEATS_PER_ROW // 2
    xs = AISLE / 2 + SEAT_PITCH / 2 + SEAT_PITCH * np.arange(half)
    xs = np.concatenate([-xs[::-1], xs])
    out = []
    for r in range(ROWS):
        y, z = FIRST_ROW_Y + r * ROW_PITCH, r * RISER
        yaw = rng.uniform(-0.04, 0.04, xs.size)  # chairs not quite square to the row
        for s, (x, a) in enumerate(zip(xs, yaw)):
            c, sn = math.cos(a), math.sin(a)
            p = model.positions
            pos = np.column_stack([c * p[:, 0] - sn * p[:, 1] + x, sn * p[:, 0] + c * p[:, 1] + y, p[:, 2] + z])
            out.append(SourceObject(f"chair_r{r:02d}_s{s:02d}", "chair", [Mesh(pos, model.faces.copy())],
                                    {"row": r, "seat": s}))
    return out


def _tour() -> tuple[list[dict], dict[str, float]]:
    """The test path: round the hall, past A, onto the stage for B, a spin at C, back to the start."""
    deg = math.pi / 180
    row = lambda r: FIRST_ROW_Y + r * ROW_PITCH  # noqa: E731
    ctl = [  # t, eye, yaw (degrees, unwrapped), pitch (degrees)
        (0.0, (0.0, 32.5, 5.5), -90, -12),  # back of the hall, high, facing the stage
        (8.0, (-12.5, 30.0, 4.2), -80, -10),  # down the left side aisle
        (17.0, (-12.0, 16.0, 3.2), -60, -12),
        (26.0, (-8.8, 7.9, 1.6), 32, -14),  # A: front-left corner, across the front rows
        (32.0, (-5.0, 5.2, 2.0), 0, -5),
        (38.0, (-9.0, 2.2, STAGE_Z + 1.7), 170, 10),  # up onto the stage
        (44.0, (-11.0, 0.0, STAGE_Z + 1.8), 215, 40),  # B: stage corner, up at bare wall and ceiling
        (50.0, (-3.0, 4.2, STAGE_Z + 1.7), 420, -5),  # turn to face the audience
        (56.0, (0.0, row(3), 3 * RISER + 1.7), 450, -6),  # into the central aisle
        (60.0, (0.0, row(10), 10 * RISER + 1.7), 450, -12),
        (60.5, (0.0, row(10), 10 * RISER + 1.7), 540, -12),  # C: a full turn in 2 s
        (61.0, (0.0, row(10), 10 * RISER + 1.7), 630, -12),
        (61.5, (0.0, row(10), 10 * RISER + 1.7), 720, -12),
        (62.0, (0.0, row(10), 10 * RISER + 1.7), 810, -12),
        (68.0, (0.0, row(18), 18 * RISER + 1.9), 810, -8),  # up the aisle to the back
        (74.0, (0.0, 32.5, 5.5), 630, -12),
    ]
    t = [c[0] for c in ctl]
    eyes = [c[1] for c in ctl]
    yaws = [c[2] * deg for c in ctl]
    pitches = [c[3] * deg for c in ctl]
    return looping_tour(t, eyes, yaws, pitches, step=0.1), {"A": 26.0, "B": 44.0, "C": 61.0}


def auditorium(seed: int = 0) -> tuple[SourceScene, list[dict], dict[str, float]]:
    """The auditorium scene, its looping tour (74 s, keys every 0.1 s) and the tour times of A, B, C.

    seed : the chairs' small yaw jitter; the same seed gives the same scene.
    Returns (scene, tour, {"A": t, "B": t, "C": t}); tour keys are
    {"t", "eye", "forward", "up"} dicts (``proto.messages.TourKey`` fields), z up.
    """
    rng = np.random.default_rng([seed, 0xA0D])
    objects = _hall() + _props() + _chairs(rng)
    tour, viewpoints = _tour()
    return SourceScene(objects=objects, sources=[f"generate:auditorium(seed={seed})"]), tour, viewpoints
