"""``bench hostile`` in short: a real replica, the real headless client, and each attack in turn."""

from __future__ import annotations

from bench.hostile import ATTACKS, MAX_RSS_GROWTH, format_table, run


def test_every_attack_leaves_the_good_client_served_and_the_replica_bounded(demo_store):
    result = run(demo_store, seconds=3.0)
    reference, *attacked = result["phases"]
    assert reference["attack"] == "none" and reference["deltas"] >= 3 and reference["errors"] == 0
    assert [p["attack"] for p in attacked] == list(ATTACKS)
    for p in attacked:
        c = p["checks"]
        # The lines that do not depend on how busy the shared machine is hold outright ...
        assert p["new_client"], p
        assert p["rss_peak"] - p["rss_before"] <= MAX_RSS_GROWTH, p
        assert p["errors"] == 0, p
        assert p["idle_after_s"] is not None and p["idle_after_s"] <= 2.0, p
        # ... the good session's deltas, loosely (a few seconds of a shared CI machine).
        assert c["delta_share"] >= 0.6, p
    assert len(format_table(result)) == 2 + len(result["phases"])
