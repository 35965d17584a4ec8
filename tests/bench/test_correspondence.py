"""bench.correspondence on a small Den Haag: sampling, the end states of a collapse-map morph, finite figures."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

from bench.correspondence import frame_box, load_pair, measure, render_images, sample_pairs
from client.renderer import Renderer
from server.scene.lod import nearest_vertex_map
from server.scene.store import SceneStore


def test_sample_pairs_are_morphing_levels_spread_over_objects(denhaag_store) -> None:
    with SceneStore.open(denhaag_store) as store:
        index = store.index
        chosen = sample_pairs(index, 12, seed=0)
        assert len(chosen) == 12 and chosen == sorted(chosen)
        assert len({o for o, _ in chosen}) == 12  # one pair per object while objects last
        for obj, k in chosen:
            rep = int(index.rep_first[obj]) + k
            assert k >= 1 and index.rep_morph[rep] and index.rep_object[rep] == obj and index.rep_level[rep] == k
        sizes = sorted(int(index.rep_vertices[index.rep_first[o] + k]) for o, k in chosen)
        all_sizes = index.rep_vertices[index.rep_morph]
        assert sizes[-1] > np.median(all_sizes)  # not only the many plain boxes
        assert sample_pairs(index, 12, seed=0) == chosen
        assert sample_pairs(index, 12, seed=1) != chosen


def test_sample_pairs_takes_more_levels_when_objects_run_out() -> None:
    # Two objects: 0 with levels 0..3 (1..3 morph), 1 with levels 0..1 (1 morphs).
    index = SimpleNamespace(
        rep_morph=np.array([0, 1, 1, 1, 0, 1], bool), rep_level=np.array([0, 1, 2, 3, 0, 1]),
        rep_object=np.array([0, 0, 0, 0, 1, 1]), rep_vertices=np.array([4, 8, 16, 32, 4, 8]),
    )
    assert sample_pairs(index, 2) and len({o for o, _ in sample_pairs(index, 2)}) == 2
    assert sample_pairs(index, 10) == [(0, 1), (0, 2), (0, 3), (1, 1)]
    with pytest.raises(ValueError):
        sample_pairs(index, 0)


def test_collapse_morph_ends_are_its_levels(denhaag_store) -> None:
    with SceneStore.open(denhaag_store) as store, Renderer(128, 128, fov_y=45.0) as renderer:
        for obj, k in sample_pairs(store.index, 4, seed=0):
            coarse, fine, collapse = load_pair(store, obj, k)
            nearest = nearest_vertex_map(fine.positions, coarse.positions)
            lo, hi = fine.positions.min(axis=0), fine.positions.max(axis=0)
            view = frame_box(lo, hi, renderer.fov_y, 1.0)
            maps = {"collapse": collapse, "nearest": nearest}
            at_one = render_images(renderer, coarse, fine, maps, view, weight=1.0, object_id=obj)
            np.testing.assert_array_equal(at_one["collapse"], at_one["fine"])
            at_zero = render_images(renderer, coarse, fine, maps, view, weight=0.0, object_id=obj)
            differ = np.abs(at_zero["collapse"].astype(int) - at_zero["coarse"]).max(axis=2) > 2
            assert differ.sum() <= 5, (obj, k, int(differ.sum()))
            assert not renderer.meshes  # the pair's reps are freed
    with pytest.raises(ValueError):
        with SceneStore.open(denhaag_store) as store:
            load_pair(store, 0, 0)


def test_measure_reports_finite_figures_and_a_winner(denhaag_store) -> None:
    ticks = []
    result = measure(denhaag_store, pairs=6, seed=0, viewport=(96, 96),
                     progress=lambda stage, done, total: ticks.append((stage, done, total)))
    json.dumps(result)  # JSON-able as it is
    rows, summary = result["rows"], result["summary"]
    assert len(rows) == summary["pairs"] == 6 and ticks[-1] == ("pairs", 6, 6)
    for row in rows:
        assert row["pixels"] > 0 and 0 <= row["maps_agree"] <= 1
        for key in ("pop", "collapse", "nearest"):
            assert math.isfinite(row[f"{key}_mad"]) and 0 <= row[f"{key}_mad"] <= 255
            assert 0 <= row[f"{key}_artefacts"] <= 1
        if row["maps_agree"] == 1.0:  # the same map draws the same image
            assert row["collapse_mad"] == row["nearest_mad"]
    for name in ("pop_mad_mean", "collapse_mad_mean", "nearest_mad_mean", "collapse_artefacts_median"):
        assert math.isfinite(summary[name])
    assert summary["pop_mad_mean"] > 0
    assert summary["winner"] in ("collapse", "nearest", "tie") and summary["margin"] >= 1.0
    assert summary["pairs_collapse_better"] + summary["pairs_nearest_better"] + summary["pairs_tied"] == 6
    assert any("winner" in line for line in result["lines"])
    assert measure(denhaag_store, pairs=6, seed=0, viewport=(96, 96))["rows"] == rows  # deterministic
