"""Screenshots that prove the appearance: the real server (uvicorn) streams user files built by
``walkstream build``'s path, the real client (EGL) draws them and writes its last frame as a PNG.

- a semantic CityJSON building (the FZK-Haus, converted from IFC): its roof's pixels are red,
  its walls' pixels light and neutral;
- a city with the ground the builder lays under it (the Berlin LoD2 blocks, which bring no
  terrain): at street level, looking slightly down, no pixel below the horizon shows the sky;
- a glTF box with a base colour factor: drawn in that colour;
- a glTF box with a red/green checkerboard base-colour texture, drawn with the ``textured``
  algorithm: both checker colours alternate along a row of its pixels; the same box without
  the texture shows the procedural pattern over its colour instead, and no checker; and the
  client offering every algorithm (its default) is sent the textured one for it.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import trimesh
from PIL import Image
from trimesh.visual.material import PBRMaterial

from bench.demo import ServerProcess
from client.app import run_client
from client.renderer import BACKGROUND
from proto.camera import projection_matrix, view_matrix
from server.scene.catalog import build_path
from server.scene.data import data_file
from server.scene.ground import ground_grid
from server.scene.importers import load_source
from server.scene.store import SceneStore

W, H, FOV = 320, 240, 60.0


CHECKER_RED, CHECKER_GREEN = (220, 30, 30), (30, 200, 40)


def _checker_box(textured: bool) -> trimesh.Trimesh:
    """A 4 m box, each face mapped onto the whole of a 256 px texture of 8 × 8 red and green squares (or,
    untextured, the same box in a plain grey)."""
    box = trimesh.creation.box((4.0, 4.0, 4.0))
    box.unmerge_vertices()
    v, f = np.asarray(box.vertices), np.asarray(box.faces)
    axis = np.argmax(np.abs(box.face_normals), axis=1)
    uv = np.zeros((len(v), 2))
    for a in range(3):
        corners = f[axis == a].ravel()
        uv[corners] = (v[corners][:, [o for o in range(3) if o != a]] + 2.0) / 4.0
    if not textured:
        box.visual = trimesh.visual.TextureVisuals(material=PBRMaterial(baseColorFactor=[150, 150, 150, 255]))
        return box
    tex = np.zeros((256, 256, 3), np.uint8)
    odd = (np.indices((256, 256)) // 32).sum(axis=0) % 2 == 1
    tex[~odd], tex[odd] = CHECKER_RED, CHECKER_GREEN
    box.visual = trimesh.visual.TextureVisuals(uv=uv, material=PBRMaterial(baseColorFactor=[255, 255, 255, 255],
                                                                           baseColorTexture=Image.fromarray(tex)))
    return box


@pytest.fixture(scope="module")
def stores(tmp_path_factory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("appearance")
    box = trimesh.creation.box((4.0, 4.0, 4.0))
    box.visual = trimesh.visual.TextureVisuals(material=PBRMaterial(baseColorFactor=[40, 90, 220, 255]))
    trimesh.Scene(box).export(folder / "bluebox.glb")
    trimesh.Scene(_checker_box(True)).export(folder / "checkerbox.glb")
    trimesh.Scene(_checker_box(False)).export(folder / "greybox.glb")
    out = {}
    for key, source in (("fzk", data_file("interior/AC20-FZK-Haus.city.json")),
                        ("berlin", data_file("trees/berlin_buildings_lod2.gml")),
                        ("box", folder / "bluebox.glb"), ("checker", folder / "checkerbox.glb"),
                        ("grey", folder / "greybox.glb")):
        out[key] = folder / f"{key}.db"
        build_path(source, out[key], workers=1)
    return out


@pytest.fixture(scope="module")
def server(stores):
    with ServerProcess(list(stores.values())) as srv:
        yield srv


def _origin(store: Path) -> tuple[str, np.ndarray]:
    with SceneStore.open(store) as s:
        return s.index.name, np.asarray(s.index.meta["origin"], np.float64)


def _shoot(server, store: Path, eye, target, path: Path, seconds: float = 5.0, sky: bool = True,
           algorithms: tuple[str, ...] | None = None) -> np.ndarray:
    """The client's last frame from a fixed pose (store coordinates) after ``seconds`` of streaming
    (``sky=False``: cleared to the plain ``BACKGROUND`` instead of the sky; ``algorithms``: those the
    client offers, default all)."""
    name, _ = _origin(store)
    forward = (np.asarray(target, float) - np.asarray(eye, float)).tolist()
    key = {"eye": list(map(float, eye)), "forward": forward, "up": [0.0, 0.0, 1.0]}
    run = run_client(server.url, name, duration=seconds, viewport=(W, H), fov_y=FOV, target_frame_time=0.25,
                     screenshot=path, tour=[{"t": 0.0, **key}, {"t": 1000.0, **key}], sky=sky,
                     **({} if algorithms is None else {"algorithms": algorithms}))
    assert not run.errors and len(run.frames) > 3
    return np.asarray(Image.open(path).convert("RGB")).astype(np.int64)


def _project(points: np.ndarray, eye, target) -> np.ndarray:
    """Pixel (column, row) of world points for the camera of ``_shoot``; rows top-down."""
    forward = np.asarray(target, float) - np.asarray(eye, float)
    vp = projection_matrix(FOV, W / H, 0.1, 1000.0) @ view_matrix(np.zeros(3), forward, np.array([0.0, 0.0, 1.0]))
    clip = np.column_stack([points - np.asarray(eye, float), np.ones(len(points))]) @ vp.T
    ndc = clip[:, :2] / clip[:, 3:4]
    return np.column_stack([(ndc[:, 0] + 1) / 2 * W, (1 - ndc[:, 1]) / 2 * H]).astype(int)


def test_a_semantic_building_has_red_roof_pixels_and_light_wall_pixels(server, stores, tmp_path) -> None:
    _, origin = _origin(stores["fzk"])
    eye, target = np.array([-22.0, -28.0, 10.0]), np.array([0.0, 0.0, 2.0])
    image = _shoot(server, stores["fzk"], eye, target, tmp_path / "fzk.png")
    source = load_source(data_file("interior/AC20-FZK-Haus.city.json"))

    def pixels(kind: str, name: str | None = None, up: float = -1.0, outer: bool = False) -> np.ndarray:
        """Image pixels at the centroids of the objects' triangles that face the camera, whose normal's z
        is at least ``up`` and, if ``outer``, that lie on the house's outer walls (its plan box)."""
        out = []
        for o in source.objects:
            info = o.attributes.get("attributes", {}).get("info", {})
            if info.get("type") != kind or (name is not None and not str(info.get("Name", "")).startswith(name)):
                continue
            m = o.levels[-1]
            tri = m.positions[m.faces] - origin
            n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            c = tri.mean(axis=1)
            length = np.linalg.norm(n, axis=1)
            facing = (n * (eye - c)).sum(axis=1) > 0.3 * length * np.linalg.norm(eye - c, axis=1)
            facing &= n[:, 2] >= up * length
            if outer:
                on_box = (np.abs(c[:, :2] - box_lo).min(axis=1) < 0.02) | (np.abs(c[:, :2] - box_hi).min(axis=1) < 0.02)
                facing &= on_box & (np.abs(n[:, 2]) < 0.05 * length)
            xy = _project(c[facing], eye, target)
            inside = (xy[:, 0] >= 0) & (xy[:, 0] < W) & (xy[:, 1] >= 0) & (xy[:, 1] < H)
            out.append(image[xy[inside, 1], xy[inside, 0]])
        return np.concatenate(out)

    walls = np.concatenate([o.levels[-1].positions for o in source.objects
                            if o.attributes.get("attributes", {}).get("info", {}).get("type") == "IfcWallStandardCase"])
    box_lo, box_hi = walls.min(axis=0)[:2] - origin[:2], walls.max(axis=0)[:2] - origin[:2]
    roof, wall = pixels("IfcSlab", "Dach", up=0.3), pixels("IfcWallStandardCase", outer=True)
    assert len(roof) >= 2 and len(wall) >= 10
    red = (roof[:, 0] > 1.6 * roof[:, 1]) & (roof[:, 0] > 1.6 * roof[:, 2])
    assert red.mean() > 0.9, roof
    neutral = (np.ptp(wall, axis=1) < 40) & (wall.min(axis=1) > 110)
    assert neutral.mean() > 0.6, wall  # windows and doors set in the walls take some of their centroids


def test_a_city_stands_on_its_generated_ground_below_the_horizon(server, stores, tmp_path) -> None:
    _, origin = _origin(stores["berlin"])
    source = load_source(data_file("trees/berlin_buildings_lod2.gml"))
    grid = ground_grid(source)
    lo = np.min([o.levels[-1].positions.min(axis=0) for o in source.objects], axis=0)
    # At street level a little west of the blocks, looking east and 8° down.
    at = np.array([lo[0] - 25.0, (lo[1] + np.max([o.levels[-1].positions[:, 1].max() for o in source.objects])) / 2])
    col = int(round((at[0] - grid.origin[0]) / grid.spacing[0]))
    row = int(round((at[1] - grid.origin[1]) / grid.spacing[1]))
    eye = np.r_[at, grid.heights[row, col] + 1.7] - origin
    pitch = math.radians(8.0)
    target = eye + np.array([math.cos(pitch), 0.0, -math.sin(pitch)])
    # Cleared to the plain background instead of the sky, so an uncovered pixel is that colour exactly.
    image = _shoot(server, stores["berlin"], eye, target, tmp_path / "street.png", sky=False)
    background = np.round(np.asarray(BACKGROUND) * 255)
    horizon = H / 2 - math.tan(pitch) / math.tan(math.radians(FOV / 2)) * H / 2  # the row of the horizon
    below = int(math.ceil(H / 2 - math.tan(pitch - math.radians(1.0)) / math.tan(math.radians(FOV / 2)) * H / 2))
    assert 10 < horizon < below < H
    bare = np.abs(image - background).max(axis=2) <= 2
    assert not bare[below:].any(), f"background below the horizon in rows {np.unique(np.nonzero(bare[below:])[0] + below)}"
    assert bare[: int(horizon) - 2].mean() > 0.2  # and still above it, between and over the blocks
    ground = image[below:].reshape(-1, 3)
    assert np.median(ground[:, 1]) > np.median(ground[:, 2])  # greenish grey (the ground), not the sky's blue


def test_a_gltf_base_colour_factor_is_drawn(server, stores, tmp_path) -> None:
    _, origin = _origin(stores["box"])
    image = _shoot(server, stores["box"], np.array([7.0, -9.0, 6.0]) - origin, -origin, tmp_path / "box.png", 3.0)
    centre = image[H // 2 - 5 : H // 2 + 5, W // 2 - 5 : W // 2 + 5].reshape(-1, 3)
    # (40, 90, 220) lit: blue dominates in every pixel, in the factor's proportions.
    assert (centre[:, 2] > 1.8 * centre[:, 0]).all() and (centre[:, 2] > 1.3 * centre[:, 1]).all()


def test_the_client_command_draws_data_colours_or_object_tints(server, stores, tmp_path) -> None:
    """``walkstream client --colour objects`` is the debugging view of tints; the default draws the data."""
    import subprocess
    import sys

    name, _ = _origin(stores["fzk"])
    red = {}
    for colour in ("data", "objects"):
        png = tmp_path / f"{colour}.png"
        done = subprocess.run([sys.executable, "-m", "walkstream", "client", server.url, "--scene", name,
                               "--duration", "4", "--width", str(W), "--height", str(H), "--target-ms", "250",
                               "--tour", "orbit",  # from above: the roof in view (its default walk goes round it)
                               "--colour", colour, "--screenshot", str(png)], capture_output=True, text=True,
                              timeout=120)
        assert done.returncode == 0, done.stderr
        image = np.asarray(Image.open(png).convert("RGB")).astype(np.int64)
        red[colour] = ((image[..., 0] > 1.6 * image[..., 1]) & (image[..., 0] > 1.6 * image[..., 2])).mean()
    assert red["data"] > 0.05 and red["objects"] < 0.01  # the roof's red; tints are pastel
    done = subprocess.run([sys.executable, "-m", "walkstream", "client", server.url, "--colour", "plaid"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "plaid" in done.stderr


def test_the_walk_tours_first_frame_stands_on_ground_below_the_horizon(server, stores, tmp_path) -> None:
    """A user's city is walked by default; the walk's first frame, at eye height looking along the street,
    shows the generated ground (never the background) everywhere below the horizon."""
    with SceneStore.open(stores["berlin"]) as s:
        tours = s.index.meta["tours"]
        assert s.index.meta["default_tour"] == "walk"
        first = tours["walk"]["keys"][0]
    eye, forward = np.asarray(first["eye"], float), np.asarray(first["forward"], float)
    forward /= np.linalg.norm(forward)
    pitch = -math.asin(forward[2])  # down is positive
    assert 0.0 <= pitch < math.radians(20.0)
    image = _shoot(server, stores["berlin"], eye, eye + forward, tmp_path / "walk.png", sky=False)
    background = np.round(np.asarray(BACKGROUND) * 255)
    t = math.tan(math.radians(FOV / 2))
    below = int(math.ceil(H / 2 - math.tan(pitch - math.radians(1.0)) / t * H / 2))  # 1° under the horizon
    assert below < H
    bare = np.abs(image - background).max(axis=2) <= 2
    assert not bare[below:].any(), f"background below the horizon in rows {np.unique(np.nonzero(bare[below:])[0] + below)}"


def _checker_kinds(row: np.ndarray) -> np.ndarray:
    """Per pixel of a row: 0 where it is the checker's red, 1 its green, −1 neither."""
    red = (row[:, 0] > 1.8 * row[:, 1]) & (row[:, 0] > 1.8 * row[:, 2])
    green = (row[:, 1] > 1.8 * row[:, 0]) & (row[:, 1] > 1.8 * row[:, 2])
    return np.where(red, 0, np.where(green, 1, -1))


def _box_rows(server, store: Path, path: Path, algorithms: tuple[str, ...] | None) -> list[np.ndarray]:
    """The box's pixels in each of the image's 20 centre rows, seen from above a corner."""
    _, origin = _origin(store)
    image = _shoot(server, store, np.array([7.0, -9.0, 6.0]) - origin, -origin, path, 4.0, sky=False,
                   algorithms=algorithms)
    background = np.round(np.asarray(BACKGROUND) * 255)
    band = image[H // 2 - 10: H // 2 + 10]
    on_box = np.abs(band - background).max(axis=2) > 2
    assert on_box.mean(axis=1).min() > 0.1, f"{path.stem}: the box covers too little of the centre rows"
    return [band[i][on_box[i]] for i in range(band.shape[0])]


def _assert_checker(rows: list[np.ndarray]) -> None:
    """Both checker colours on the box in every row, alternating along it: a checker, not two coloured faces."""
    switches = []
    for row in rows:
        kinds = _checker_kinds(row)
        assert (kinds == 0).mean() > 0.2 and (kinds == 1).mean() > 0.2, "not both checker colours in a row"
        k = kinds[kinds >= 0]
        switches.append(int(np.count_nonzero(np.diff(k))))
    assert min(switches) >= 3


def test_a_textured_gltf_draws_its_texture_and_an_untextured_one_the_procedural_pattern(server, stores,
                                                                                         tmp_path) -> None:
    """Drawn with the textured algorithm only: the checker box's pixels alternate red and green along a row;
    the grey box's (the same box without the texture) are its grey under the bricks, never the checker."""
    rows = {key: _box_rows(server, stores[key], tmp_path / f"{key}.png", ("textured",)) for key in ("checker", "grey")}
    _assert_checker(rows["checker"])
    for row in rows["grey"]:
        assert (_checker_kinds(row) < 0).all()
        assert np.ptp(row.mean(axis=1)) > 5  # the procedural pattern, not a flat colour


def test_the_client_offering_every_algorithm_draws_the_texture(server, stores, tmp_path) -> None:
    """The normal client offers flat, lit and textured; with time to spare the selection draws the checker box
    textured (drawn lit it would be the checker's mean colour, a plain brownish box)."""
    _assert_checker(_box_rows(server, stores["checker"], tmp_path / "checker_all.png", None))
