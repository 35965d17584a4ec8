"""Funkhouser & Séquin's test scene: an auditorium of 440 detailed chairs, and their test path.

The paper's auditorium held 87,565 polygons, most of them in hundreds of copies
of one chair; drawn in full (method None) it took 0.43 s per frame against a
0.1 s target — 4.3× the target on average, 9.9× at worst (FORMULAS.md, Table 1).
This scene reproduces that *ratio*, not the polygon count: with a
250-triangle chair (this module's VERSION 1, 110k triangles) a software
rasteriser drew the whole hall in full at about a 50 ms target, so no budget
bound. The hall (floor,
raked seating tiers, walls, ceiling, stage, a few props) now holds 20 rows × 22
copies of one 5,632-triangle chair, 2.48 M triangles in all, so that drawn in
full the tour costs several times a 50 ms target, most at A and with the whole
hall in view, least round B (the README's evaluation gives the measured frame
times). "On average over the tour" weights each frame by how long it lasted —
F&S sampled their path evenly; a client in wall-clock time draws most of its
frames in the cheap stretch round B, so its plain per-frame mean is lower.

The chair is eighteen separate closed parts — turned legs with bevelled feet,
a domed cushion with a rolled front edge, five curved slats, posts and rails
following the back's curve, armrests with domed ends on turned supports — so
quadric decimation has real detail to take away: the builder's chain halves it
seven times (5,632 → 44 triangles). The four finest levels
(down to 704) are whole chairs within 1.2 cm of full detail, 352 is a chair
without its slats (8 cm); below that the simplifier drops whole parts — levels
for far chairs and for budgets below the cost of the whole hall at 352.

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

__all__ = ["auditorium", "chair_mesh", "VERSION", "ROWS", "SEATS_PER_ROW"]

#: Bumped when the scene changes, so cached stores built from an older one are rebuilt.
#: 2: the 5,632-triangle chair, 2.48 M triangles (1: 248 triangles, 110k in all).
VERSION = 2

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


def _closed(positions: np.ndarray, faces: np.ndarray) -> trimesh.Trimesh:
    """One closed part, coincident vertices merged, wound outward (checked: the simplifier needs volumes)."""
    m = trimesh.Trimesh(positions, faces, process=True)
    if m.volume < 0:
        m.invert()
    if not m.is_volume:
        raise RuntimeError("a chair part is not a closed, consistently wound surface")
    return m


def _rounding(half: float, r: float, band: int, flat: int) -> np.ndarray:
    """Grid coordinates along one axis of a rounded box: ``flat`` samples on the flat, ``band`` per rounded end.

    The band steps are r·tan(θ) for evenly spaced θ ∈ (0, 45°], so once the grid is pushed onto the rounded
    surface its vertices sit at even angles round each edge.
    """
    core = half - r
    step = r * np.tan(np.linspace(0.0, math.pi / 4, band + 1)[1:])
    return np.concatenate([-core - step[::-1], np.linspace(-core, core, flat), core + step])


def _rounded_box(ext, radius: float, band: int = 2, flat=(2, 2, 2)) -> trimesh.Trimesh:
    """A box of extents ``ext`` centred on the origin whose edges and corners are rounded with ``radius``.

    A grid on the six faces (``_rounding`` coordinates) pushed onto the Minkowski sum of a smaller box and a
    sphere: triangles are densest where the surface bends, which is what decimation removes first.
    """
    half = np.asarray(ext, np.float64) / 2
    r = min(radius, 0.999 * float(half.min()))
    axes = [_rounding(half[i], r, band, flat[i]) for i in range(3)]
    positions, faces, n = [], [], 0
    for a in range(3):
        b, c = (a + 1) % 3, (a + 2) % 3
        u, v = np.meshgrid(axes[b], axes[c], indexing="ij")
        idx = np.arange(u.size).reshape(u.shape)
        q0, q1, q2, q3 = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
        quad = np.concatenate([np.stack([q0, q1, q2], -1), np.stack([q0, q2, q3], -1)]).reshape(-1, 3)
        for side in (-1.0, 1.0):
            p = np.empty(u.shape + (3,))
            p[..., a], p[..., b], p[..., c] = side * half[a], u, v
            positions.append(p.reshape(-1, 3))
            faces.append(n + (quad if side > 0 else quad[:, ::-1]))
            n += u.size
    p = np.concatenate(positions)
    core = half - r
    inner = np.clip(p, -core, core)
    d = p - inner
    length = np.linalg.norm(d, axis=1, keepdims=True)
    return _closed(inner + r * d / np.where(length > 0, length, 1.0), np.concatenate(faces))


def _section(width: float, depth: float, k: int = 8, power: float = 4.0) -> np.ndarray:
    """A rounded-rectangle cross-section (a superellipse), k points (k, 2) counter-clockwise."""
    a = np.linspace(0.0, 2 * math.pi, k, endpoint=False) + math.pi / k
    c, s = np.cos(a), np.sin(a)
    e = 2.0 / power
    return np.column_stack([width / 2 * np.sign(c) * np.abs(c) ** e, depth / 2 * np.sign(s) * np.abs(s) ** e])


def _sweep(section: np.ndarray, path: np.ndarray, side, scale=None) -> trimesh.Trimesh:
    """A closed tube: ``section`` (k, 2) carried along ``path`` (n, 3), its first axis kept along ``side``.

    ``scale`` (n,) sizes the section at each path point (rounded ends); ends are capped with a fan round
    the path's end points.
    """
    path = np.asarray(path, np.float64)
    if scale is not None:
        section = np.asarray(scale, np.float64)[:, None, None] * section[None]
    tangent = np.gradient(path, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    u = np.asarray(side, np.float64) - (tangent @ np.asarray(side, np.float64))[:, None] * tangent
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(tangent, u)
    section = np.broadcast_to(section, (path.shape[0],) + section.shape[-2:])
    rings = path[:, None, :] + section[:, :, :1] * u[:, None, :] + section[:, :, 1:] * v[:, None, :]
    n, k = rings.shape[:2]
    idx = np.arange(n * k).reshape(n, k)
    nxt = np.roll(idx, -1, axis=1)
    a, b, c, d = idx[:-1], idx[1:], nxt[1:], nxt[:-1]
    tube = np.concatenate([np.stack([a, b, c], -1), np.stack([a, c, d], -1)]).reshape(-1, 3)
    first, last = n * k, n * k + 1
    caps = np.concatenate([np.column_stack([np.full(k, first), idx[0], nxt[0]]),
                           np.column_stack([np.full(k, last), nxt[-1], idx[-1]])])
    return _closed(np.concatenate([rings.reshape(-1, 3), path[[0, -1]]]), np.concatenate([tube, caps]))


def _lathe(profile, sections: int) -> trimesh.Trimesh:
    """A closed solid of revolution about z from a (radius, z) profile that starts and ends on the axis."""
    m = trimesh.creation.revolve(np.asarray(profile, np.float64), sections=sections)
    return _closed(np.asarray(m.vertices), np.asarray(m.faces))


BACK_ARC = 0.6  #: radius of the chair back's curve seen from above (m)


def _back_y(z: np.ndarray) -> np.ndarray:
    """The back's profile seen from the side: leaning back 0.12 m per metre, with a lumbar bulge forward."""
    return 0.22 + 0.12 * (z - 0.5) - 0.02 * np.sin(math.pi * np.clip((z - 0.5) / 0.45, 0.0, 1.0))


def _arc_y(x: np.ndarray) -> np.ndarray:
    """How far the back curves away (+y) at x across it, on the ``BACK_ARC`` circle."""
    return BACK_ARC * (1.0 - np.cos(np.asarray(x) / BACK_ARC))


def chair_mesh() -> Mesh:
    """The chair model (5,632 triangles), seat front toward −y, feet at z = 0, centred on x = y = 0.

    Eighteen separate closed parts: four turned legs with bevelled feet, a domed cushion with a rolled
    front edge, five slats, two posts and two rails following the back's curve (bowed seen from above,
    leaning back with a lumbar bulge seen from the side), two armrests with domed ends on turned
    supports. Triangles are densest where the surface bends, which is what decimation takes first.
    """
    parts: list[trimesh.Trimesh] = []
    leg_profile = [(0.0, 0.0), (0.019, 0.0), (0.023, 0.006), (0.023, 0.016), (0.018, 0.03), (0.015, 0.2),
                   (0.016, 0.3), (0.019, 0.31), (0.017, 0.36), (0.02, 0.4), (0.02, 0.42), (0.0, 0.42)]
    for sx in (-0.21, 0.21):
        for sy in (-0.19, 0.19):
            parts.append(_lathe(leg_profile, 16).apply_translation((sx, sy, 0.0)))
    cushion = _rounded_box((0.5, 0.46, 0.075), 0.03, band=3, flat=(7, 7, 3))
    p = cushion.vertices.copy()
    top = np.clip(p[:, 2] / 0.0375, 0.0, 1.0)
    p[:, 2] += 0.012 * top * np.clip(1 - (p[:, 0] / 0.25) ** 2, 0, 1) * np.clip(1 - (p[:, 1] / 0.23) ** 2, 0, 1)
    p[:, 2] -= 0.03 * np.clip((-p[:, 1] - 0.1) / 0.13, 0.0, 1.0)  # waterfall front edge
    parts.append(_closed(p + (0.0, 0.0, 0.4525), cushion.faces))
    z = np.linspace(0.53, 0.9, 12)
    slat = _section(0.05, 0.016, k=10)
    for x in np.linspace(-0.16, 0.16, 5):
        a = x / BACK_ARC
        path = np.column_stack([np.full_like(z, x), _back_y(z) + _arc_y(x), z])
        parts.append(_sweep(slat, path, (math.cos(a), math.sin(a), 0.0)))
    zp = np.linspace(0.4, 0.99, 12)
    for sx in (-0.23, 0.23):
        a = sx / BACK_ARC
        path = np.column_stack([np.full_like(zp, sx), _back_y(zp) + _arc_y(sx), zp])
        parts.append(_sweep(_section(0.04, 0.035, k=10), path, (math.cos(a), math.sin(a), 0.0)))
    xr = np.linspace(-0.21, 0.21, 14)
    for zr, size in ((0.515, (0.035, 0.03)), (0.93, (0.065, 0.035))):
        path = np.column_stack([xr, _back_y(np.full_like(xr, zr)) + _arc_y(xr), np.full_like(xr, zr)])
        parts.append(_sweep(_section(*size, k=10), path, (0.0, 0.0, 1.0)))
    # armrests: straight along y, the front end dipping a little, both ends domed (quarter circles of 2 cm)
    dome = np.radians([30.0, 60.0, 90.0])
    end = 0.02 * (1.0 - np.cos(dome))
    ya = np.concatenate([-0.23 + end, np.linspace(-0.19, 0.23, 6), 0.27 - end[::-1]])
    za = 0.66 - 0.012 * np.clip((-ya - 0.1) / 0.13, 0.0, 1.0) ** 2
    arm_scale = np.concatenate([np.sin(dome), np.ones(6), np.sin(dome)[::-1]])
    for sx in (-0.27, 0.27):
        parts.append(_sweep(_section(0.06, 0.04, k=12), np.column_stack([np.full_like(ya, sx), ya, za]),
                            (1.0, 0.0, 0.0), arm_scale))
        support = [(0.0, 0.0), (0.014, 0.0), (0.012, 0.09), (0.014, 0.18), (0.016, 0.2), (0.0, 0.2)]
        parts.append(_lathe(support, 12).apply_translation((sx, -0.14, 0.44)))
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
