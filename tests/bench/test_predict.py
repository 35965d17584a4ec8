"""``bench.predict``: prediction error against horizon on camera tours, beside the zero-order hold."""

from __future__ import annotations

import json
import math

import pytest

from bench.predict import run, tours_from_stores


def _key(t, eye, forward):
    return {"t": t, "eye": list(eye), "forward": list(forward), "up": [0.0, 0.0, 1.0]}


#: A long straight walk at 2 m/s (sampled for 20 s, so it never loops back).
STRAIGHT = [_key(0.0, (0, 0, 2), (1, 0, 0)), _key(100.0, (200, 0, 2), (1, 0, 0))]
#: Straight for 8 s, a 90° turn over 2 s, straight again.
TURN = [
    _key(0.0, (0, 0, 2), (1, 0, 0)),
    _key(8.0, (16, 0, 2), (1, 0, 0)),
    _key(9.0, (18, 1, 2), (1, 1, 0)),
    _key(10.0, (18, 3, 2), (0, 1, 0)),
    _key(30.0, (18, 43, 2), (0, 1, 0)),
]


def _rows(result, scene):
    return sorted((r for r in result["rows"] if r["scene"] == scene), key=lambda r: r["horizon"])


def test_synthetic_tours():
    ticks = []
    result = run([("straight", STRAIGHT), ("turn", TURN)], duration=20.0, jitter=0.02, seed=1,
                 progress=lambda stage, done, total: ticks.append((stage, done, total)))
    json.dumps(result)  # JSON-able
    assert result["config"]["horizons"] == [0.25, 0.5, 1.0, 1.5, 2.0]
    assert {r["scene"] for r in result["rows"]} == {"straight", "turn", "all"}
    for r in result["rows"]:
        assert all(math.isfinite(v) for k, v in r.items() if isinstance(v, float))
    for scene, keys in (("straight", ("pos_mean", "hold_pos_mean")),
                        ("turn", ("pos_mean", "hold_pos_mean", "ang_mean", "hold_ang_mean"))):
        rows = _rows(result, scene)
        assert len(rows) == 5
        for key in keys:
            assert all(b[key] > a[key] for a, b in zip(rows, rows[1:])), (scene, key)
    straight = _rows(result, "straight")
    for r in straight:  # constant velocity: the line is right, holding is 2 m/s × h off
        assert r["pos_ratio"] < 0.1 and r["pos_p95"] < 0.2  # jitter 2 cm per axis: the slope's noise × h
        assert r["hold_pos_mean"] == pytest.approx(2.0 * r["horizon"], abs=0.05)
    turn = _rows(result, "turn")
    # following a turn beats holding the direction; far ahead, the line overshoots where the turn ends
    assert all(r["ang_ratio"] < 1.0 for r in turn if r["horizon"] <= 1.0)
    assert turn[-1]["ang_mean"] > straight[-1]["ang_mean"]
    # progress: per scene, ending at its total
    assert {s for s, _, _ in ticks} == {"predict straight", "predict turn"}
    assert ticks[-1][1] == ticks[-1][2] == 401
    assert len(result["lines"]) == 3 + len(result["rows"])


def test_bad_arguments():
    with pytest.raises(ValueError):
        run([])
    with pytest.raises(ValueError):
        run([("s", STRAIGHT)], rate=0.0)
    with pytest.raises(ValueError):
        run([("s", STRAIGHT)], horizons=(0.0,))


def test_demo_store_tour(demo_store):
    scenes = tours_from_stores([demo_store])
    assert scenes[0][0] == "demo" and len(scenes[0][1]) > 2
    result = run(scenes, horizons=(0.5, 1.5))
    rows = _rows(result, "demo")
    assert len(rows) == 2 and rows[1]["pos_mean"] > rows[0]["pos_mean"]
    assert all(r["pos_ratio"] < 0.5 and r["ang_ratio"] < 1.0 for r in rows)


def test_cli_prints_both_parts_as_json(demo_store, denhaag_store):
    import json
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-m", "walkstream", "bench", "predict", "--store", str(demo_store),
                           "--city", str(denhaag_store), "--pairs", "4", "--kiosk-store", str(demo_store),
                           "--kiosk-seconds", "0", "--json"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    figures = json.loads(done.stdout)
    rows = figures["prediction"]["rows"]
    assert {r["horizon"] for r in rows} == {0.25, 0.5, 1.0, 1.5, 2.0}
    assert figures["correspondence"]["summary"]["winner"] in ("collapse", "nearest", "tie")
    assert "Prediction error against horizon" in done.stderr and "winner:" in done.stderr
    kiosk = figures["kiosk"]["predict"]["rows"]  # tour-aware against linear on a kiosk tour of the garden
    assert kiosk and all(r["plan_pos_ratio"] < 1e-3 for r in kiosk) and "plan/lin" in done.stderr
    assert "image" not in figures["kiosk"]


def test_cli_refuses_a_bad_kiosk_option(tmp_path):
    import subprocess
    import sys

    for args, words in ((["--kiosk-seconds", "1"], "--kiosk-seconds"), (["--kiosk-viewport", "big"], "WxH")):
        done = subprocess.run([sys.executable, "-m", "walkstream", "bench", "predict", "--pairs", "0", *args],
                              capture_output=True, text=True, timeout=60)
        assert done.returncode == 2 and words in done.stderr


def test_cli_refuses_a_missing_store(tmp_path):
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-m", "walkstream", "bench", "predict", "--store", str(tmp_path / "no.db"),
                           "--pairs", "0"], capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "no such store" in done.stderr
