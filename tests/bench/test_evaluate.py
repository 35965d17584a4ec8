"""bench.evaluate: the run plan, one real evaluation on a small scene, the summaries, scene resolution."""

from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest

from bench.evaluate import (
    RunSpec,
    evaluate,
    plan,
    print_table,
    scene_has_continuous,
    skipped_methods,
    summarize_frames,
    table_rows,
    tour_of,
)
from bench.methods import METHODS
from bench.stores import resolve_scene
from server.scene.store import SCHEMA_VERSION, SceneStore

SCHEMA_TOP = {"scene", "store", "target_ms", "budgets_ms", "viewport", "fov_y", "tau_s", "seed", "duration_s",
              "warmup_s", "viewpoints", "methods", "runs", "images"}
SCHEMA_RUN = {"method", "target_ms", "solver", "predict", "morph", "frames", "quality", "summary"}
SCHEMA_FRAMES = {"t", "time_ms", "compute_ms", "triangles", "reps", "bytes", "morphs", "predicted_ms",
                 "governor_predicted_ms", "governor_bound", "governor_aim", "governor_quantile"}
SCHEMA_SUMMARY = {"frames", "compute_mean_ms", "compute_max_ms", "frame_mean_ms", "frame_max_ms", "frame_std_ms",
                  "frame_p95_ms", "triangles_mean", "reps_mean", "bytes_total", "flip_mean", "psnr_mean",
                  "ssim_mean", "popping_mean", "errors", "late", "deltas"}


# ---------------------------------------------------------------- plan


def _names(specs):
    return [(s.method.name, s.target_ms) for s in specs]


def test_plan_runs_baselines_once_others_per_budget_and_drops_mixed_without_trees():
    specs = plan(None, 50.0, None, continuous=False, governor=False)
    assert _names(specs) == [
        ("none", 50.0), ("static", 50.0),
        ("feedback", 25.0), ("feedback", 50.0), ("feedback", 100.0),
        ("optimization", 25.0), ("optimization", 50.0), ("optimization", 100.0),
        ("hierarchical", 25.0), ("hierarchical", 50.0), ("hierarchical", 100.0),
        ("predictive", 25.0), ("predictive", 50.0), ("predictive", 100.0),
    ]
    assert skipped_methods(None, continuous=False) == {"mixed": "no continuous objects"}
    with_trees = plan(None, 50.0, None, continuous=True, governor=False)
    assert _names(with_trees)[-3:] == [("mixed", 25.0), ("mixed", 50.0), ("mixed", 100.0)]
    assert skipped_methods(None, continuous=True) == {}


def test_plan_includes_the_target_among_the_budgets_and_keeps_the_order_given():
    specs = plan(["optimization", "static"], 40.0, [100.0, 20.0], governor=False)
    assert _names(specs) == [("optimization", 20.0), ("optimization", 40.0), ("optimization", 100.0),
                             ("static", 40.0)]
    assert plan(["static"], 40.0, [100.0]) == [RunSpec(METHODS["static"], 40.0)]


def test_plan_runs_budgeted_methods_with_and_without_the_governor_and_interleaves_repeats():
    specs = plan(["static", "optimization"], 50.0, [50.0], repeats=3)
    one = [("static", 50.0, False), ("optimization", 50.0, False), ("optimization", 50.0, True)]
    assert [(s.method.name, s.target_ms, s.governor) for s in specs] == one * 3  # A B C A B C A B C
    assert [s.repeat for s in specs] == [0, 0, 0, 1, 1, 1, 2, 2, 2]
    with pytest.raises(ValueError, match="repeats"):
        plan(["static"], 50.0, None, repeats=0)


def test_methods_are_the_issue_s_and_ask_the_sessions_the_papers_way():
    assert list(METHODS) == ["none", "static", "feedback", "optimization", "hierarchical", "predictive", "mixed"]
    from server.select.solvers import SOLVERS

    for m in METHODS.values():
        assert m.solver in SOLVERS, m
    assert not any(METHODS[n].predict or METHODS[n].morph for n in ("none", "static", "feedback", "optimization",
                                                                     "hierarchical"))
    pred = METHODS["predictive"]
    assert (pred.solver, pred.predict, pred.morph) == ("hierarchical", True, True)
    assert METHODS["mixed"].continuous_only and METHODS["mixed"].predict and METHODS["mixed"].morph
    assert [n for n, m in METHODS.items() if not m.budget_dependent] == ["none", "static"]


@pytest.mark.parametrize("kwargs, match", [
    (dict(methods=["fastest"], target_ms=50.0, budgets_ms=None), "unknown method"),
    (dict(methods=[], target_ms=50.0, budgets_ms=None), "no methods"),
    (dict(methods=None, target_ms=0.0, budgets_ms=None), "positive"),
    (dict(methods=None, target_ms=50.0, budgets_ms=[25.0, -1.0]), "positive"),
    (dict(methods=["static", "static"], target_ms=50.0, budgets_ms=None), "twice"),
])
def test_plan_refuses_bad_input(kwargs, match):
    with pytest.raises(ValueError, match=match):
        plan(kwargs["methods"], kwargs["target_ms"], kwargs["budgets_ms"])


# ---------------------------------------------------------------- summaries


def test_summary_counts_frames_after_warmup_that_draw_and_each_selection_once():
    frames = {
        "t": [0.5, 1.0, 2.0, 2.5, 3.0, 3.5, 4.0],
        "seq": [-1, 1, 1, 2, 2, 2, 3],
        "time_ms": [1.0, 90.0, 40.0, 50.0, 60.0, 50.0, 40.0],
        "compute_ms": [0.0, 9.0, 9.0, 3.0, 3.0, 3.0, 5.0],
        "triangles": [0, 10, 20, 30, 40, 50, 60],
        "reps": [0, 1, 2, 3, 4, 5, 6],
        "bytes": [0, 1000, 0, 200, 0, 0, 100],
    }
    s = summarize_frames(frames, warmup=2.0, target_ms=50.0)
    ms = np.array([40.0, 50.0, 60.0, 50.0, 40.0])
    assert s["frame_p99_ms"] == pytest.approx(np.percentile(ms, 99))
    assert s["over_pct"] == pytest.approx(20.0)  # one frame of five over 55 ms
    assert summarize_frames(frames, warmup=2.0)["over_pct"] is None  # no target, no share
    assert s["frames"] == 5
    assert s["frame_mean_ms"] == pytest.approx(ms.mean())
    assert s["frame_max_ms"] == 60.0
    assert s["frame_std_ms"] == pytest.approx(ms.std())
    assert s["frame_p95_ms"] == pytest.approx(np.percentile(ms, 95))
    # selections first drawn after the warm-up: 2 (3 ms) and 3 (5 ms); 1 was first drawn at t = 1.0
    assert s["selections"] == 2
    assert s["compute_mean_ms"] == pytest.approx(4.0) and s["compute_max_ms"] == 5.0
    assert s["triangles_mean"] == pytest.approx(40.0) and s["reps_mean"] == pytest.approx(4.0)
    assert s["bytes_total"] == 300


def test_summary_of_no_frames_is_empty_not_an_error():
    s = summarize_frames({k: [] for k in ("t", "seq", "time_ms", "compute_ms", "triangles", "reps", "bytes")})
    assert s["frames"] == 0 and s["frame_mean_ms"] is None and s["compute_max_ms"] is None
    assert s["bytes_total"] == 0


# ---------------------------------------------------------------- a real evaluation


def _recompute(frames: dict, warmup: float) -> dict:
    """The summary figures from the frame lists, written out plainly (no shared code with the module)."""
    rows = [i for i, t in enumerate(frames["t"]) if t >= warmup and frames["seq"][i] >= 0]
    ms = [frames["time_ms"][i] for i in rows]
    mean = sum(ms) / len(ms)
    firsts = [i for i in rows if i == 0 or frames["seq"][i] != frames["seq"][i - 1]]
    compute = [frames["compute_ms"][i] for i in firsts]
    return {
        "frames": len(rows), "frame_mean_ms": mean, "frame_max_ms": max(ms),
        "frame_std_ms": math.sqrt(sum((m - mean) ** 2 for m in ms) / len(ms)),
        "compute_mean_ms": sum(compute) / len(compute), "compute_max_ms": max(compute),
        "triangles_mean": sum(frames["triangles"][i] for i in rows) / len(rows),
        "reps_mean": sum(frames["reps"][i] for i in rows) / len(rows),
        "bytes_total": sum(b for t, b in zip(frames["t"], frames["bytes"]) if t >= warmup),
    }


def test_evaluate_runs_every_spec_on_a_real_server_and_client(demo_store):
    ticks = []
    res = evaluate(demo_store, methods=["none", "static", "optimization"], budgets_ms=[50.0], duration=3.0,
                   warmup=1.0, viewport=(160, 90), quality=False, progress=lambda *a: ticks.append(a), repeats=1)
    assert SCHEMA_TOP <= set(res)
    json.dumps(res, allow_nan=False)  # plain, JSON-serialisable
    assert res["scene"] == "demo" and res["methods"] == ["none", "static", "optimization"]
    assert res["budgets_ms"] == [50.0] and res["images"] == {}  # no quality pass: no false-colour views
    # The demo names no viewpoints: A and C get stand-ins on the tour, after the warm-up, each with its reason.
    assert set(res["viewpoints"]) == {"A", "C"} == set(res["viewpoints_derived"])
    assert all(1.0 <= t <= 3.0 for t in res["viewpoints"].values())
    assert res["duration_s"] == 3.0 and res["seed"] == 0 and res["skipped"] == {}
    specs = plan(res["methods"], 50.0, [50.0], continuous=False)
    assert [(r["method"], r["target_ms"]) for r in res["runs"]] == _names(specs)
    assert ticks[0] == ("runs", 0, 4) and ticks[-1] == ("runs", 4, 4)
    assert [r["governor"] for r in res["runs"]] == [False, False, False, True]
    assert res["algorithms"] == ["lit"] and res["repeats"] == 1
    if len(os.sched_getaffinity(0)) >= 2:  # server and client were put on different cores
        assert res["cores"] and not set(res["cores"]["server"]) & set(res["cores"]["client"])
    for run in res["runs"]:
        c = run["calibration"]  # timed once a second beside the run: at least at its start and after 1 s
        assert len(c["t"]) == len(c["ms"]) >= 2 and all(ms > 0 for ms in c["ms"])
        assert run["summary"]["calibration_median_ms"] > 0
    for run in res["runs"]:
        assert SCHEMA_RUN <= set(run)
        m = METHODS[run["method"]]
        assert (run["solver"], run["predict"], run["morph"]) == (m.solver, m.predict, m.morph)
        f = run["frames"]
        assert SCHEMA_FRAMES <= set(f)
        n = len(f["t"])
        assert n > 0 and all(len(v) == n for v in f.values())
        assert all(math.isfinite(x) and x > 0 for x in f["time_ms"])
        assert f["t"] == sorted(f["t"])
        assert any(c > 0 for c in f["compute_ms"]), run["method"]
        assert sum(f["bytes"]) > 0
        # The governor's own prediction of each frame is recorded where it governs, and nowhere else.
        assert any(p > 0 for p in f["governor_predicted_ms"]) == run["governor"], run["method"]
        assert run["governor"] or not any(f["governor_bound"])
        # ... and so is the aim it steered to, a share of the target within the governor's own limits.
        if run["governor"]:
            assert all(0.5 <= a <= 1.0 for a in f["governor_aim"]), run["method"]
            assert all(0.5 <= q < 1.0 for q in f["governor_quantile"]), run["method"]
        else:
            assert not any(f["governor_aim"]) and not any(f["governor_quantile"])
        assert run["quality"]["flip"] == [] and run["quality"]["frame"] == []
        s = run["summary"]
        assert SCHEMA_SUMMARY <= set(s)
        assert s["errors"] == 0 and s["deltas"] >= 1
        assert s["flip_mean"] is None and s["popping_mean"] is None
        for key, value in _recompute(f, res["warmup_s"]).items():
            assert s[key] == pytest.approx(value), (run["method"], key)
        assert s["frame_p95_ms"] == pytest.approx(np.percentile(
            [x for t, q, x in zip(f["t"], f["seq"], f["time_ms"]) if t >= 1.0 and q >= 0], 95))
    # None draws every object at full detail: never fewer triangles than Static, over the same tour
    by = {r["method"]: r["summary"] for r in res["runs"] if not r["governor"]}
    assert by["none"]["triangles_mean"] >= by["static"]["triangles_mean"]

    from rich.console import Console

    console = Console(record=True, width=220)
    print_table(res, console)
    text = console.export_text()
    assert all(name in text for name in res["methods"])
    assert [r["method"] for r in table_rows(res)] == res["methods"] + ["optimization+gov"]


def test_evaluate_refuses_bad_settings_before_starting_a_server(demo_store):
    with pytest.raises(ValueError, match="warm-up"):
        evaluate(demo_store, methods=["static"], duration=1.0, warmup=2.0, quality=False)
    with pytest.raises(ValueError, match="τ"):
        evaluate(demo_store, methods=["static"], tau=0.0, quality=False)
    with pytest.raises(ValueError, match="unknown method"):
        evaluate(demo_store, methods=["fastest"], quality=False)


# ---------------------------------------------------------------- scenes


def test_tour_and_continuous_objects_of_a_store(demo_store):
    keys, viewpoints, length = tour_of(demo_store)
    assert keys and length == max(k["t"] for k in keys) and length > 0
    assert viewpoints == {}
    assert scene_has_continuous(demo_store) is False


def test_resolve_scene_opens_a_store(demo_store):
    assert resolve_scene(demo_store) == (demo_store, "demo")
    assert resolve_scene(str(demo_store)) == (demo_store, "demo")


def test_resolve_scene_builds_a_named_scene_once_into_the_cache(tmp_path, monkeypatch):
    import server.scene.catalog as catalog
    from server.scene.demo import build_demo

    calls = []

    def small(name, path, *, seed=0, progress=None, **_):  # the real recipe at a test's size
        calls.append((name, seed))
        return build_demo(path, objects=6, seed=seed)

    monkeypatch.setattr(catalog, "build_named", small)
    path, name = resolve_scene("demo", seed=4, cache_dir=tmp_path)
    assert path == tmp_path / f"demo-s4-v{SCHEMA_VERSION}-b{catalog.BUILD_VERSION}.db" and path.is_file()
    assert name == "demo"
    assert resolve_scene("demo", seed=4, cache_dir=tmp_path) == (path, "demo")
    assert calls == [("demo", 4)]  # the second time it was cached


def test_a_store_cached_by_an_older_build_is_built_anew_and_left_in_place(tmp_path, monkeypatch):
    import server.scene.catalog as catalog
    from server.scene.demo import build_demo

    calls = []

    def small(name, path, *, seed=0, progress=None, **_):
        calls.append(name)
        return build_demo(path, objects=6, seed=seed)

    monkeypatch.setattr(catalog, "build_named", small)
    monkeypatch.setattr(catalog, "BUILD_VERSION", catalog.BUILD_VERSION - 1)
    old, _ = resolve_scene("demo", seed=1, cache_dir=tmp_path)
    monkeypatch.setattr(catalog, "BUILD_VERSION", catalog.BUILD_VERSION + 1)  # a build that makes more
    new, name = resolve_scene("demo", seed=1, cache_dir=tmp_path)
    assert new != old and new.is_file() and name == "demo"
    assert calls == ["demo", "demo"]  # the old store was not reused...
    assert old.is_file()  # ...nor deleted

    source = tmp_path / "box.obj"
    import trimesh

    trimesh.creation.box().export(source)
    first, _ = resolve_scene(source, cache_dir=tmp_path / "files")
    monkeypatch.setattr(catalog, "BUILD_VERSION", catalog.BUILD_VERSION + 1)
    second, _ = resolve_scene(source, cache_dir=tmp_path / "files")
    assert second != first and first.is_file() and second.is_file()


@pytest.mark.parametrize("suffix", ["obj", "ply"])
def test_resolve_scene_builds_a_user_file_with_a_generated_tour(tmp_path, suffix):
    import trimesh

    source = tmp_path / f"my model.{suffix}"
    trimesh.creation.icosphere(subdivisions=2, radius=3.0).export(source)
    cache = tmp_path / "cache"
    path, name = resolve_scene(source, cache_dir=cache)
    assert path.parent == cache and path.is_file() and name == "my model"
    with SceneStore.open(path) as s:
        assert s.index.n_objects >= 1
    keys, _, length = tour_of(path)
    assert len(keys) > 1 and length > 0
    built = path.stat().st_mtime_ns
    assert resolve_scene(source, cache_dir=cache) == (path, name) and path.stat().st_mtime_ns == built
    trimesh.creation.box(extents=(2, 3, 4)).export(source)  # new content, new store
    assert resolve_scene(source, cache_dir=cache)[0] != path


def test_resolve_scene_says_what_is_wrong(tmp_path):
    with pytest.raises(ValueError, match="no such scene store"):
        resolve_scene(tmp_path / "missing.db", cache_dir=tmp_path)
    with pytest.raises(ValueError, match="neither a scene store"):
        resolve_scene(tmp_path / "missing.obj", cache_dir=tmp_path)
    with pytest.raises(ValueError, match="neither a scene store"):
        resolve_scene("atlantis", cache_dir=tmp_path)
    notes = tmp_path / "notes.txt"
    notes.write_text("hello")
    with pytest.raises(ValueError, match="not a scene store"):
        resolve_scene(notes, cache_dir=tmp_path)
    fake = tmp_path / "fake.db"
    fake.write_bytes(b"not sqlite")
    with pytest.raises(ValueError, match="not a usable scene store"):
        resolve_scene(fake, cache_dir=tmp_path)
    broken = tmp_path / "broken.obj"
    broken.write_text("v 1 2\nf 1 2 9\n")
    with pytest.raises(ValueError, match="cannot build"):
        resolve_scene(broken, cache_dir=tmp_path / "cache")


def test_a_scene_without_viewpoints_gets_stand_ins_for_a_and_c(denhaag_store) -> None:
    from bench.evaluate import derive_viewpoints
    from bench.scenarios.paths import visible_counts
    from proto.tour import Tour
    from server.scene.store import SceneStore

    got = derive_viewpoints(denhaag_store, 20.0, 2.0)
    assert set(got) == {"A", "C"} and all(2.0 <= t <= 20.0 for t, _ in got.values())
    with SceneStore.open(denhaag_store) as s:
        tour = Tour(list(s.index.tour))
        ts = np.arange(2.5, 19.5 + 1e-9, 0.5)
        counts = visible_counts(s.index, tour.pose_at(ts), 60.0, (640, 360))
    assert counts[list(ts).index(got["A"][0])] == counts.max()  # A: the most in view
    assert derive_viewpoints(denhaag_store, 20.0, 2.0, missing=["C"]).keys() == {"C"}
    assert derive_viewpoints(denhaag_store, 20.0, 2.0, missing=[]) == {}
