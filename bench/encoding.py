"""``walkstream bench encoding``: bytes on the wire against raw float32, on real scene stores.

Every payload is the one the server streams (stored as sent). Raw is what a
naive sender would ship: float32 xyz (12 B) per vertex and three uint32 (12 B)
per triangle for meshes; float32 xyz + radius, float32 normal and RGBA8 per
point for tree models; a uint32 model id and a float32 3 × 4 matrix per tree
instance. The reference measured in the same run is zstd (level 3) of those raw
arrays — general-purpose compression without quantization or the vertex-cache
order meshoptimizer's codecs exploit.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Callable

import numpy as np
import zstandard

from proto.geometry import decode_geometry
from proto.morph import decode_morph
from proto.points import decode_instances, decode_points
from server.scene.index import TREES
from server.scene.store import SceneStore

__all__ = ["measure", "run"]

GOAL = 0.40  # the goal: at most 40 % of the raw float32 bytes


def _raw_mesh(blob: bytes) -> bytes:
    g = decode_geometry(blob)
    return np.ascontiguousarray(g.positions, np.float32).tobytes() + np.ascontiguousarray(g.indices, np.uint32).tobytes()


def measure(path: Path, progress: Callable[[str, int, int], None] | None = None) -> dict:
    """Per kind (meshes, morph maps, tree models, tree groups): payload bytes, raw bytes, zstd-of-raw bytes."""
    zc = zstandard.ZstdCompressor(level=3)
    out: dict[str, dict] = {}
    with SceneStore.open(path) as store:
        idx = store.index
        m = idx.n_representations
        trees = np.asarray(idx.object_kind)[np.asarray(idx.rep_object)] == TREES
        meshes = np.nonzero(~trees)[0]
        groups = np.nonzero(trees)[0]

        def tally(kind: str, payload: int, raw: int, zstd_raw: int) -> None:
            row = out.setdefault(kind, {"count": 0, "bytes": 0, "raw": 0, "zstd_raw": 0})
            row["count"] += 1
            row["bytes"] += payload
            row["raw"] += raw
            row["zstd_raw"] += zstd_raw

        done, total = 0, m + int(idx.model_points.shape[0])
        for chunk in np.array_split(meshes, max(1, meshes.size // 256)) if meshes.size else []:
            ids = chunk.tolist()
            for blob, mm in zip(store.geometries(ids), store.morphs(ids)):
                raw = _raw_mesh(blob)
                tally("mesh", len(blob), len(raw), len(zc.compress(raw)))
                if mm:
                    # A morph map names one coarser vertex per vertex: raw is an int32 per vertex.
                    vmap = np.ascontiguousarray(decode_morph(mm), np.int32).tobytes()
                    tally("morph", len(mm), len(vmap), len(zc.compress(vmap)))
            done += len(ids)
            if progress:
                progress(idx.name, done, total)
        for chunk in np.array_split(groups, max(1, groups.size // 256)) if groups.size else []:
            for blob in store.geometries(chunk.tolist()):
                inst = decode_instances(blob)
                raw = (np.ascontiguousarray(inst.model, np.uint32).tobytes()
                       + np.ascontiguousarray(inst.matrix, np.float32).tobytes())
                tally("trees", len(blob), len(raw), len(zc.compress(raw)))
            done += chunk.size
            if progress:
                progress(idx.name, done, total)
        for blob in store.model_geometries(range(int(idx.model_points.shape[0]))):
            pts = decode_points(blob)
            raw = (np.ascontiguousarray(pts.positions, np.float32).tobytes()
                   + np.ascontiguousarray(pts.radius, np.float32).tobytes()
                   + np.ascontiguousarray(pts.normals, np.float32).tobytes()
                   + np.ascontiguousarray(pts.colors, np.uint8).tobytes())
            tally("models", len(blob), len(raw), len(zc.compress(raw)))
            done += 1
            if progress:
                progress(idx.name, done, total)
    geometry = [k for k in ("mesh", "morph", "trees", "models") if k in out]
    all_bytes = sum(out[k]["bytes"] for k in geometry)
    all_raw = sum(out[k]["raw"] for k in geometry)
    all_zstd = sum(out[k]["zstd_raw"] for k in geometry)
    for row in out.values():
        row["ratio"] = row["bytes"] / row["raw"] if row["raw"] else None
        row["zstd_ratio"] = row["zstd_raw"] / row["raw"] if row["raw"] and row["zstd_raw"] else None
    return {"store": str(path), "scene": idx.name, "kinds": out, "bytes": all_bytes, "raw": all_raw,
            "ratio": all_bytes / all_raw if all_raw else None,
            "zstd_ratio": all_zstd / all_raw if all_raw else None,
            "vs_zstd": all_bytes / all_zstd if all_zstd else None}


def wire(path: Path, keys: int | None = 30) -> dict:
    """Bytes of the delta frames a session really sends over the scene's tour (``proto.codec.encode``: zstd
    over each large frame) against the raw float32 of the geometry those deltas carry."""
    from proto import PROTOCOL_VERSION
    import msgpack

    from proto.codec import COMPRESS_ABOVE, decode_server, encode
    from proto.messages import Camera, Delta, Hello, Pong
    from server.select import kernels
    from server.session import Session, SessionConfig

    # Select with the compiled kernels, as a server does from its start (it waits for them too).
    kernels.warm_up(setting=os.environ.get("WALKSTREAM_NUMBA"))
    with SceneStore.open(path) as store:
        idx = store.index
        verts = np.asarray(idx.rep_vertices, np.int64)
        faces = np.asarray(idx.rep_faces, np.int64)
        trees = np.asarray(idx.object_kind)[np.asarray(idx.rep_object)] == TREES
        s = Session({idx.name: store}, "wire", SessionConfig(bandwidth=1e9), stopwatch=time.perf_counter)
        s.receive(Hello(protocol=PROTOCOL_VERSION, scene=idx.name, viewport=[1280, 720], predict=False,
                        algorithms=["flat", "lit", "textured"]), 0.0)
        s.receive(Pong(id=1, sent=0.0, t=0.0), 0.0)
        tour = idx.tour[: keys or len(idx.tour)]
        frame_bytes = plain_bytes = raw = whole = 0
        zc = zstandard.ZstdCompressor(level=3)
        for i, key in enumerate(tour):
            now = float(i)
            s.receive(Camera(t=now, eye=key["eye"], forward=key["forward"], up=key["up"]), now)
            for m in s.poll(max(now, s.next_deadline() or now)):
                if not isinstance(m, Delta) or not m.add:
                    continue
                frame = encode(m)
                assert decode_server(frame).seq == m.seq
                # The geometry's share of the frame: the adds and models alone, as the codec would send them.
                geo = msgpack.packb([a.model_dump() for a in m.add] + [x.model_dump() for x in m.models],
                                    use_bin_type=True)
                packed = zc.compress(geo)
                frame_bytes += min(len(packed), len(geo)) if len(geo) > COMPRESS_ABOVE else len(geo)
                plain_bytes += len(geo)
                whole += len(frame)
                for a in m.add:
                    if trees[a.rep]:
                        inst = decode_instances(a.geometry)
                        raw += 4 * inst.model.size + 48 * inst.model.size
                    else:
                        raw += 12 * int(verts[a.rep]) + 12 * int(faces[a.rep]) + (4 * int(verts[a.rep]) if a.morph else 0)
                for mod in m.models:
                    n = decode_points(mod.points).positions.shape[0]
                    raw += n * (12 + 4 + 12 + 4)
    return {"scene": idx.name, "frames": frame_bytes, "uncompressed": plain_bytes, "raw": raw, "whole_frames": whole,
            "ratio": frame_bytes / raw if raw else None, "zstd_saving": 1 - frame_bytes / plain_bytes if plain_bytes else None}


def run(paths: list[Path], progress: Callable[[str, int, int], None] | None = None, keys: int | None = 30) -> dict:
    rows = [measure(p, progress) for p in paths]
    wires = [wire(p, keys) for p in paths]
    lines = [f"{'scene':<12} {'kind':<7} {'count':>7} {'payload':>11} {'raw f32':>11} {'ratio':>7} "
             f"{'zstd(raw)':>9}"]
    for r in rows:
        for kind, k in r["kinds"].items():
            zr = f"{k['zstd_ratio']:.3f}" if k["zstd_ratio"] else "—"
            lines.append(f"{r['scene']:<12} {kind:<7} {k['count']:>7} {k['bytes']:>11,} {k['raw']:>11,} "
                         f"{k['ratio']:>7.3f} {zr:>9}")
        lines.append(f"{r['scene']:<12} {'all':<7} {'':>7} {r['bytes']:>11,} {r['raw']:>11,} {r['ratio']:>7.3f} "
                     f"{r['zstd_ratio']:>9.3f}   ({r['vs_zstd']:.2f}× the zstd reference; goal ≤ {GOAL:.2f})")
    lines.append("")
    lines.append(f"{'on the wire':<12} {'geometry':>13} {'(no zstd)':>11} {'raw f32':>11} {'ratio':>7}  "
                 f"(what deltas carried over the first {keys} tour keys at 1280×720)")
    for w in wires:
        lines.append(f"{w['scene']:<12} {w['frames']:>13,} {w['uncompressed']:>11,} {w['raw']:>11,} {w['ratio']:>7.3f}"
                     f"   zstd saves {100 * w['zstd_saving']:.0f} %; whole delta frames {w['whole_frames']:,} B")
    worst = max(w["ratio"] for w in wires)
    return {"scenes": rows, "wire": wires, "worst_ratio": worst, "goal": GOAL, "met": worst <= GOAL, "lines": lines}
