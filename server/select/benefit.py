"""Benefit of drawing an object tuple (Funkhouser & Séquin 1993, section 5; Zach 2002, 4.2).

Benefit(O, L, R) = Size(O) · Accuracy(O, L, R) · Importance(O) · Focus(O) · Motion(O) · Hysteresis(O, L, R).

Size is the pixels the object covers; every other factor is a multiplier in
(0, 1] that can only take benefit away (F&S keep them in [0, 1]; here they
never reach 0, so a drawn object is always worth something and values stay
finite). Accuracy is F&S's 1 − BaseError / Samples^m, with Samples and m set
by the rendering algorithm, Zach's face-density ratio, or the screen-space
error: each level's stored geometric error projected to pixels (as Cesium and
Nanite select by it), 1 / (1 + error in pixels). A representation that
carries a base-colour texture loses accuracy when drawn by an algorithm that
does not sample it (``texture_accuracy``): the same for every accuracy model,
so the texture's detail counts whichever measures the shape. Everything is arrays
over all candidate tuples at once: (n,) per object, (n, K) per option, where
option k is level k // R with algorithm k % R (see ``solvers.candidates``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace

import numpy as np

from proto.messages import ALGORITHMS

__all__ = [
    "BASE_ERROR",
    "ALGORITHM_EXPONENT",
    "ALGORITHM_SAMPLES",
    "MIN_FACTOR",
    "ACCURACY_MODES",
    "DEFAULT_ACCURACY",
    "resolved_accuracy",
    "UNTEXTURED_ACCURACY",
    "TEXTURE_ALGORITHMS",
    "accuracy",
    "algorithm_accuracy",
    "texture_accuracy",
    "zach_accuracy",
    "projected_error",
    "screen_error_accuracy",
    "original_faces",
    "importance",
    "importance_table",
    "focus",
    "motion",
    "hysteresis",
    "BenefitFactors",
    "benefit_matrix",
    "benefit",
]

BASE_ERROR = 0.5

#: F&S's exponent m per interpolation method: flat = 1, Gouraud = 2. Textured
#: surfaces are Gouraud-lit here, so they interpolate like "lit".
ALGORITHM_EXPONENT = {"flat": 1.0, "lit": 2.0, "textured": 2.0}

#: What F&S count as Samples(L, R): polygons for flat shading, vertices for
#: Gouraud (lit, textured); never more than the pixels covered.
ALGORITHM_SAMPLES = {"flat": "faces", "lit": "vertices", "textured": "vertices"}

#: Accuracy of a textured representation drawn without its texture (flat, lit: its mean colour), against
#: the same level drawn with it. The mean colour keeps the surface's shape and shading and loses the
#: texture's detail, an error the image shows wherever the surface does; counting the shape and the
#: detail as equal halves of what the image shows makes that half. At this value the texture wins per
#: unit cost too (``cost.ALGORITHM_SCALE`` prices a textured vertex 1.2× a lit one), so with time to spare a
#: textured surface is drawn textured, while a tight budget can still settle for a cheaper algorithm
#: at a finer level. Untextured representations are untouched: the procedural pattern the textured
#: algorithm draws on them is not their appearance.
UNTEXTURED_ACCURACY = 0.5

#: The rendering algorithms that sample a representation's own texture.
TEXTURE_ALGORITHMS = frozenset({"textured"})

#: ``BenefitFactors.accuracy`` values; "auto" lets the view choose (``resolved_accuracy``).
ACCURACY_MODES = ("auto", "fs", "zach", "sse", "off")

#: What "auto" accuracy means where the levels' geometric errors are known: the simplest model whose
#: rank correlation with the measured image error is within 10 % of the best (``bench benefit``).
DEFAULT_ACCURACY = "sse"

#: The floor of every qualitative factor: a multiplier in (0, 1] never reaches 0.
MIN_FACTOR = 1e-3


# ----------------------------------------------------------------------------- accuracy


def accuracy(samples: np.ndarray, m: float = 1.0) -> np.ndarray:
    """float64 in [0.5, 1): 1 − 0.5 / samples^m; more samples, diminishing returns (shape follows input)."""
    samples = np.maximum(np.asarray(samples, np.float64), 1.0)
    return 1.0 - BASE_ERROR / samples**m


def algorithm_accuracy(
    size: np.ndarray,
    faces: np.ndarray,
    vertices: np.ndarray | None = None,
    algorithms: int = 1,
    exponent: dict[str, float] | None = None,
    names: tuple[str, ...] = ALGORITHMS,
) -> np.ndarray:
    """(n, K) F&S accuracy of each tuple, Samples and m chosen by the option's rendering algorithm.

    size : (n,) pixels covered — caps Samples ("never more than #pixels")
    faces, vertices : (n, K) polygons / vertices of each option's level (vertices None: use faces)
    algorithms : R; option k is drawn with ``names[k % R]``
    """
    exponent = ALGORITHM_EXPONENT if exponent is None else exponent
    faces = np.asarray(faces, np.float64)
    verts = faces if vertices is None else np.broadcast_to(np.asarray(vertices, np.float64), faces.shape)
    k = faces.shape[-1]
    alg = np.arange(k) % algorithms
    per_vertex = np.array([ALGORITHM_SAMPLES.get(names[r], "faces") == "vertices" for r in range(algorithms)])
    m = np.array([float(exponent[names[r]]) for r in range(algorithms)])
    samples = np.where(per_vertex[alg], verts, faces)
    pixels = np.asarray(size, np.float64)
    if pixels.ndim == faces.ndim - 1:
        pixels = pixels[..., None]
    samples = np.minimum(samples, np.maximum(pixels, 1.0))
    return accuracy(samples, m[alg])


def texture_accuracy(textured: np.ndarray, algorithms: int = 1, names: tuple[str, ...] = ALGORITHMS,
                     untextured: float = UNTEXTURED_ACCURACY) -> np.ndarray:
    """(n, K) float64 the accuracy left to each option by its algorithm's treatment of the texture.

    textured : (n, K) bool — the option's representation carries a base-colour texture
    algorithms : R; option k is drawn with ``names[k % R]``
    ``untextured`` (``UNTEXTURED_ACCURACY``) where a textured representation is drawn by an algorithm
    outside ``TEXTURE_ALGORITHMS``, 1 everywhere else.
    """
    textured = np.asarray(textured, bool)
    samples = np.array([names[r] in TEXTURE_ALGORITHMS for r in range(algorithms)])
    loses = textured & ~samples[np.arange(textured.shape[-1]) % algorithms]
    return np.where(loses, float(untextured), 1.0)


def zach_accuracy(screen_size: np.ndarray, faces: np.ndarray, original_faces: np.ndarray) -> np.ndarray:
    """Zach 2002's accuracy, max(1, S / #originalFaces) / max(1, S / #faces), in (0, 1].

    screen_size : S, estimated pixels of the representation's bounding box
    faces : polygons of the representation r_ij
    original_faces : polygons of the object's full-detail model
    A representation with at least one face per pixel is as good as the original
    (accuracy 1); below that, accuracy falls in proportion to its face count.
    Inputs broadcast against each other.
    """
    s = np.asarray(screen_size, np.float64)
    f = np.maximum(np.asarray(faces, np.float64), 1.0)
    o = np.maximum(np.asarray(original_faces, np.float64), 1.0)
    return np.maximum(1.0, s / o) / np.maximum(1.0, s / f)


def projected_error(error: np.ndarray, size: np.ndarray, extent: np.ndarray) -> np.ndarray:
    """Pixels a level's object-space geometric error spans on screen, from the object's projected size.

    error  : object-space geometric error of each option (``SceneIndex.rep_error``), (n, K) or (n,)
    size   : (n,) pixels the object's box covers (``camera.screen_size``)
    extent : (n,) the box's diagonal, object-space units
    The box's diagonal spans about √(2·size) pixels at the object's distance, so a length e
    spans e / extent · √(2·size): the distance and the projection come in through the size.
    """
    err = np.maximum(np.asarray(error, np.float64), 0.0)
    size = np.maximum(np.asarray(size, np.float64), 0.0)
    extent = np.maximum(np.asarray(extent, np.float64), 1e-12)
    per = np.sqrt(2.0 * size) / extent
    if per.ndim == err.ndim - 1:
        per = per[..., None]
    return err * per


def screen_error_accuracy(error_px: np.ndarray) -> np.ndarray:
    """1 / (1 + error in pixels), in (0, 1]: full detail (no error) is 1, a level whose error spans one
    pixel is worth half its size; diminishing returns as the error shrinks below a pixel."""
    return 1.0 / (1.0 + np.maximum(np.asarray(error_px, np.float64), 0.0))


def original_faces(finest: np.ndarray, parent: np.ndarray | None = None) -> np.ndarray:
    """(n,) float64 Zach's #originalFaces per row: the full-detail faces of the part of the scene it stands for.

    finest : (n,) faces of each row's finest level
    parent : (n,) parent row, −1 for roots (a hierarchy), or None (independent chains: ``finest``)
    A hierarchy node stands for its subtree: the sum of its leaves' finest faces
    (never less than its own finest level). Summed bottom-up one tree depth at a
    time (a ``bincount`` per depth), not per node.
    """
    finest = np.asarray(finest, np.float64).reshape(-1)
    if parent is None:
        return finest.copy()
    parent = np.asarray(parent, np.int64).reshape(-1)
    n = finest.shape[0]
    if parent.shape != (n,):
        raise ValueError(f"parent must be ({n},) like finest; got {parent.shape}")
    if np.any((parent < -1) | (parent >= n)):
        raise ValueError(f"parent rows must be −1 (root) or in 0..{n - 1}")
    depth = np.zeros(n, np.int64)
    up = parent.copy()
    alive = np.nonzero(up >= 0)[0]
    while alive.size:  # every node walks up to its root at once: one pass per tree level
        if depth[alive[0]] >= n:
            raise ValueError("parent links form a cycle")
        depth[alive] += 1
        up[alive] = parent[up[alive]]
        alive = alive[up[alive] >= 0]
    has_parent = parent >= 0
    leaf = np.bincount(parent[has_parent], minlength=n) == 0
    total = np.where(leaf, finest, 0.0)
    for d in range(int(depth.max(initial=0)), 0, -1):  # deepest first: a child is complete before it is added
        rows = np.nonzero(depth == d)[0]
        total += np.bincount(parent[rows], weights=total[rows], minlength=n)
    return np.maximum(total, finest)


# ----------------------------------------------------------------------------- qualitative factors


def importance(object_class: np.ndarray, table: np.ndarray) -> np.ndarray:
    """(n,) semantic weight of each object's class (walls before pencils); classes outside the table weigh 1."""
    cls = np.asarray(object_class, np.int64)
    table = np.asarray(table, np.float64)
    if table.size and not (np.isfinite(table).all() and (table > 0).all() and (table <= 1).all()):
        raise ValueError("importance weights must lie in (0, 1]")
    known = (cls >= 0) & (cls < table.size)
    return np.where(known, table[np.where(known, cls, 0)] if table.size else 1.0, 1.0)


def importance_table(class_names: list[str] | tuple[str, ...], weights: dict[str, float], default: float = 1.0) -> np.ndarray:
    """(C,) float64 importance per class id, from weights by class name (missing names get ``default``)."""
    table = np.array([float(weights.get(name, default)) for name in class_names], np.float64)
    if not (np.isfinite(table).all() and (table > 0).all() and (table <= 1).all()):
        raise ValueError("importance weights must lie in (0, 1]")
    return table


def focus(offset: np.ndarray, strength: float = 0.3) -> np.ndarray:
    """1 − strength · offset, floored at MIN_FACTOR: benefit falls with distance from the screen centre.

    offset : distance from the screen centre in [0, 1] (``camera.centre_offset``)
    """
    offset = np.clip(np.asarray(offset, np.float64), 0.0, 1.0)
    return np.maximum(1.0 - strength * offset, MIN_FACTOR)


def motion(speed_px_s: np.ndarray, polygon_px: np.ndarray, strength: float = 0.5, frame_time: float = 0.05) -> np.ndarray:
    """1 / (1 + strength · blur): benefit falls with apparent speed relative to the average polygon.

    speed_px_s : apparent screen speed, pixels per second (``camera.screen_speed``), (n,) or (n, K)
    polygon_px : average polygon area in pixels (object's pixels / polygons), broadcastable
    blur : polygons crossed per frame = speed · frame_time / √polygon_px. The reduction is
    proportional to it while small (F&S) and never reaches 0.
    """
    speed = np.maximum(np.asarray(speed_px_s, np.float64), 0.0)
    edge = np.sqrt(np.maximum(np.asarray(polygon_px, np.float64), 1.0))
    return 1.0 / (1.0 + strength * speed * frame_time / edge)


def hysteresis(
    option: np.ndarray,
    previous: np.ndarray,
    algorithms: int = 1,
    level_weight: float = 0.1,
    algorithm_weight: float = 0.1,
) -> np.ndarray:
    """(n, K) in (0, 1]: 1 / (1 + level_weight·|ΔL| + algorithm_weight·|ΔR|) from the previous tuple.

    option : (K,) or (n, K) option indices (level · R + algorithm)
    previous : (n,) option drawn last time, −1 for none (those objects get 1 everywhere)
    Changing the level or the algorithm from frame to frame is bothersome, so the
    previous tuple keeps its full benefit and others lose in proportion to the change.
    """
    prev = np.asarray(previous, np.int64)[:, None]
    opt = np.asarray(option, np.int64)
    if opt.ndim == 1:
        opt = opt[None, :]
    d_level = np.abs(opt // algorithms - prev // algorithms)
    d_alg = np.abs(opt % algorithms - prev % algorithms)
    h = 1.0 / (1.0 + level_weight * d_level + algorithm_weight * d_alg)
    return np.where(prev >= 0, h, 1.0)


# ----------------------------------------------------------------------------- the product


@dataclass(frozen=True)
class BenefitFactors:
    """Which factors of the F&S product are on, and how strongly each bites.

    accuracy : "fs" (1 − 0.5/Samples^m), "zach" (face density), "sse" (screen-space error), "off", or "auto" (the default:
        "zach" on the hierarchical view, "fs" on the flat one — see the module docstring)
    exponent : m per rendering algorithm name (F&S accuracy)
    *_strength / *_weight : slope of each qualitative factor; defaults are mild so that
    Size · Accuracy dominates (an object at the corner keeps 70 % of its benefit).
    frame_time : seconds per frame, turns screen speed into blur per frame (Motion)
    """

    size: bool = True
    accuracy: str = "auto"
    exponent: dict = field(default_factory=lambda: dict(ALGORITHM_EXPONENT))
    algorithm_names: tuple = ALGORITHMS
    importance: bool = True
    focus: bool = True
    focus_strength: float = 0.3
    motion: bool = True
    motion_strength: float = 0.5
    frame_time: float = 0.05
    hysteresis: bool = True
    level_weight: float = 0.1
    algorithm_weight: float = 0.1

    def __post_init__(self) -> None:
        if self.accuracy not in ACCURACY_MODES:
            raise ValueError(f"accuracy must be one of {ACCURACY_MODES}, got {self.accuracy!r}")
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, float) or (isinstance(v, int) and not isinstance(v, bool)):
                if not (math.isfinite(v) and v >= 0):
                    raise ValueError(f"{f.name} must be finite and non-negative, got {v}")
        for name, m in self.exponent.items():
            if not (math.isfinite(m) and m >= 0):
                raise ValueError(f"exponent[{name!r}] must be finite and non-negative, got {m}")
        missing = [a for a in self.algorithm_names if a not in self.exponent]
        if missing:
            raise ValueError(f"no accuracy exponent for algorithms {missing}")


def resolved_accuracy(factors: BenefitFactors, hierarchical: bool = False, errors: bool = False) -> BenefitFactors:
    """``factors`` with "auto" accuracy made concrete: ``DEFAULT_ACCURACY`` where the view holds its levels'
    geometric errors (``errors``), else "zach" for the hierarchical view and "fs" for the flat one.

    An explicit setting is returned unchanged. The resolved copies are kept on
    ``factors`` (a session passes the same object every τ; validating a new one costs ~50 µs).
    """
    if factors.accuracy != "auto":
        return factors
    cache = vars(factors).setdefault("_resolved", {})
    key = (hierarchical, errors)
    if key not in cache:
        mode = DEFAULT_ACCURACY if errors else ("zach" if hierarchical else "fs")
        cache[key] = replace(factors, accuracy=mode)
    return cache[key]


def with_algorithms(factors: BenefitFactors, algorithms) -> BenefitFactors:
    """``factors`` naming the offered rendering algorithms (indices into ``proto.messages.ALGORITHMS``), kept on
    ``factors`` as ``resolved_accuracy`` keeps its copies (a session asks for the same one every τ)."""
    from proto.messages import ALGORITHMS

    key = tuple(int(a) for a in algorithms)
    cache = vars(factors).setdefault("_named", {})
    if key not in cache:
        cache[key] = replace(factors, algorithm_names=tuple(ALGORITHMS[a] for a in key))
    return cache[key]


def benefit_matrix(
    size: np.ndarray,
    faces: np.ndarray,
    *,
    algorithms: int = 1,
    factors: BenefitFactors = BenefitFactors(),
    vertices: np.ndarray | None = None,
    original_faces: np.ndarray | None = None,
    object_class: np.ndarray | None = None,
    importance_table: np.ndarray | None = None,
    offset: np.ndarray | None = None,
    speed: np.ndarray | None = None,
    previous: np.ndarray | None = None,
    error: np.ndarray | None = None,
    extent: np.ndarray | None = None,
    textured: np.ndarray | None = None,
) -> np.ndarray:
    """(n, K) float64 Benefit = Size · Accuracy · Importance · Focus · Motion · Hysteresis.

    size : (n,) pixels each object covers
    faces, vertices : (n, K) polygons / vertices of each option's level (option k: level k // R,
        algorithm k % R with R = ``algorithms``)
    original_faces : (n,) full-detail polygons for Zach's accuracy (None: each row's largest ``faces``;
        a hierarchy node's are its subtree's, ``original_faces``)
    object_class, importance_table : (n,) class id, (C,) weight per class — Importance
    offset : (n,) distance from the screen centre in [0, 1] — Focus
    speed : (n,) apparent screen speed, px/s — Motion (against each option's average polygon)
    previous : (n,) option drawn last time, −1 none — Hysteresis
    error, extent : (n, K) object-space geometric error of each option, (n,) box diagonal — "sse" accuracy
    textured : (n, K) bool, the option's representation carries a texture — part of Accuracy
        (``texture_accuracy``), with every accuracy model but "off"; None: nothing is textured
    A factor is skipped when switched off in ``factors`` or when its input is None; "auto" accuracy
    is F&S's here (the selection resolves it per view, ``resolved_accuracy``).
    """
    size = np.asarray(size, np.float64)
    faces = np.asarray(faces, np.float64)
    if faces.ndim != 2 or size.shape != faces.shape[:1]:
        raise ValueError(f"size must be (n,) and faces (n, K); got {size.shape}, {faces.shape}")
    if algorithms < 1 or algorithms > len(factors.algorithm_names):
        raise ValueError(f"algorithms must be in 1..{len(factors.algorithm_names)}, got {algorithms}")
    out = np.ones(faces.shape, np.float64)
    if factors.size:
        out *= size[:, None]
    if factors.accuracy in ("fs", "auto"):
        out *= algorithm_accuracy(size, faces, vertices, algorithms, factors.exponent, factors.algorithm_names)
    elif factors.accuracy == "zach":
        orig = faces.max(axis=1) if original_faces is None else np.asarray(original_faces, np.float64)
        out *= zach_accuracy(size[:, None], faces, orig[:, None])
    elif factors.accuracy == "sse":
        if error is None or extent is None:
            raise ValueError("screen-space error accuracy needs each option's error and the objects' extent")
        out *= screen_error_accuracy(projected_error(error, size, extent))
    if factors.accuracy != "off" and textured is not None:
        out *= texture_accuracy(textured, algorithms, factors.algorithm_names)
    if factors.importance and object_class is not None and importance_table is not None:
        out *= importance(object_class, importance_table)[:, None]
    if factors.focus and offset is not None:
        out *= focus(offset, factors.focus_strength)[:, None]
    if factors.motion and speed is not None:
        # Motion(O) is the object's, as F&S write it: measured against its coarsest level's average
        # polygon, the same for every level. Per level (against each level's own polygons) it made every
        # finer level worth less than a coarser one, and moving cameras ratcheted all objects to level 0.
        polygon_px = size / np.maximum(faces[:, 0], 1.0)
        out *= motion(np.asarray(speed, np.float64), polygon_px, factors.motion_strength, factors.frame_time)[:, None]
    if factors.hysteresis and previous is not None:
        # A change forgoes the share 1 − Hysteresis of the benefit it gains (or loses that share more).
        # Applied to the whole benefit, as F&S's multiplier is, 10 % a level outweighed the accuracy
        # differences between levels (≪ 1 % above ~100 faces) and froze every object at its level.
        keep = hysteresis(np.arange(faces.shape[1]), previous, algorithms, factors.level_weight, factors.algorithm_weight)
        prev = np.asarray(previous, np.int64)
        had = (prev >= 0) & (prev < faces.shape[1])
        at_prev = np.where(had, out[np.arange(out.shape[0]), np.clip(prev, 0, faces.shape[1] - 1)], 0.0)[:, None]
        out = np.where(had[:, None], out - (1.0 - keep) * np.abs(out - at_prev), out)
    return out


def benefit(size: np.ndarray, faces: np.ndarray, m: float = 1.0) -> np.ndarray:
    """(k,) float64 benefit of representations with ``faces`` polygons on objects covering ``size`` pixels.

    The skeleton's Size · Accuracy (flat shading), kept for the callers that use it.
    """
    return np.asarray(size, np.float64) * accuracy(faces, m)
