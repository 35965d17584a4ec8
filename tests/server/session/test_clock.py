"""The server's view of the client's clock: offset and round trip from pings, bandwidth from acks."""

from __future__ import annotations

import pytest

from server.clock import ClockSync, Delivery


def test_the_smallest_round_trip_gives_the_offset():
    clock = ClockSync()
    assert clock.client_time(10.0) == 10.0 and not clock.known
    clock.observe(client_t=105.3, received=5.0)  # before any pong: a first guess from a stamped message
    assert clock.offset == pytest.approx(100.3)
    # client = server + 100; one-way delays (0.05, 0.05), then an asymmetric (0.01 out, 0.4 back) pair.
    clock.add(sent=10.0, client_t=110.05, received=10.1)
    clock.add(sent=20.0, client_t=120.01, received=20.41)
    assert clock.known
    assert clock.rtt == pytest.approx(0.1) and clock.offset == pytest.approx(100.0)
    assert clock.server_time(clock.client_time(3.0)) == pytest.approx(3.0)


def test_the_offset_follows_the_samples_kept_and_restored():
    """The best sample is kept between pings: it must follow samples that age out and a restored snapshot."""
    clock = ClockSync(keep=2)
    clock.add(sent=0.0, client_t=100.05, received=0.1)  # rtt 0.1, offset 100
    clock.add(sent=1.0, client_t=201.1, received=1.2)  # rtt 0.2, offset 200
    assert clock.offset == pytest.approx(100.0)
    clock.add(sent=2.0, client_t=302.15, received=2.3)  # rtt 0.3: the 0.1 sample ages out
    assert clock.rtt == pytest.approx(0.2) and clock.offset == pytest.approx(200.0)
    other = ClockSync(keep=2)
    other.add(sent=0.0, client_t=0.01, received=0.02)  # a better sample, then replaced by the snapshot
    assert other.rtt == pytest.approx(0.02)
    other.from_state(clock.to_state())
    assert other.rtt == pytest.approx(0.2) and other.offset == pytest.approx(200.0)


def test_bad_samples_are_ignored():
    clock = ClockSync()
    clock.add(sent=5.0, client_t=1.0, received=4.0)  # negative round trip
    clock.add(sent=5.0, client_t=float("nan"), received=5.1)
    assert not clock.known


def test_delivery_follows_the_bandwidth_acks_imply():
    clock = ClockSync()
    clock.add(sent=0.0, client_t=0.05, received=0.1)  # offset 0, rtt 0.1
    d = Delivery(bandwidth=1e9)
    for seq in range(1, 6):  # 1 MB deltas taking 0.02 s to select, 0.05 s one way and 1 s on the wire
        d.sent(seq, server_now=10.0 * seq, nbytes=1_000_000, select_time=0.02)
        took = d.acked(seq, client_t=10.0 * seq + 0.02 + 0.05 + 1.0, clock=clock)
        assert took == pytest.approx(1.07)
    assert d.bandwidth == pytest.approx(1e6, rel=1e-6)
    assert d.estimate(500_000, clock) == pytest.approx(0.05 + 0.5)
    assert d.acked(99, 1.0, clock) is None  # an ack for nothing sent is ignored
