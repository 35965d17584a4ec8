"""The redial backoff: exponential, capped, jittered within [step/2, step], the random source injected."""

from __future__ import annotations

import math
import random

import pytest
from hypothesis import given
from hypothesis import strategies as st

from client.connection import BACKOFF, Backoff, as_urls

unit = st.floats(0.0, 1.0, exclude_max=True)


@given(base=st.floats(0.001, 1.0), factor=st.floats(1.0, 1000.0), draws=st.lists(unit, min_size=1, max_size=40))
def test_waits_double_to_the_cap_and_stay_within_the_jitter_band(base: float, factor: float,
                                                                 draws: list[float]) -> None:
    cap = base * factor
    source = iter(draws)
    backoff = Backoff(base, cap, random=lambda: next(source))
    assert backoff.wait(0) == 0.0  # the first round starts at once
    steps = [backoff.step(r) for r in range(1, len(draws) + 1)]
    for r, (u, step) in enumerate(zip(draws, steps), start=1):
        assert step == min(cap, base * 2 ** (r - 1))
        wait = backoff.wait(r)
        assert step / 2 <= wait <= step <= cap
        assert wait == pytest.approx(step * (0.5 + 0.5 * u))
    assert steps == sorted(steps)


def test_a_fleet_redialling_together_spreads_out() -> None:
    """Kiosks cut off at once draw their waits apart: no two of a hundred redial in step."""
    waits = [Backoff(random=random.Random(seed).random).wait(8) for seed in range(100)]
    assert len(set(waits)) == 100
    assert max(waits) - min(waits) > 0.3 * BACKOFF[1]


def test_the_step_never_overflows_however_long_the_outage() -> None:
    assert Backoff().step(10**9) == BACKOFF[1]


@pytest.mark.parametrize("base, cap", [(0.0, 1.0), (-1.0, 1.0), (math.nan, 1.0), (1.0, 0.5), (0.1, math.inf)])
def test_bad_backoffs_are_refused_naming_the_field(base: float, cap: float) -> None:
    with pytest.raises(ValueError, match="^(base|cap): "):
        Backoff(base, cap)


def test_one_url_or_several() -> None:
    assert as_urls("ws://a/ws") == ("ws://a/ws",)
    assert as_urls(["ws://a/ws", "ws://b/ws"]) == ("ws://a/ws", "ws://b/ws")
    for bad in ([], "", ["ws://a/ws", ""]):
        with pytest.raises(ValueError, match="^urls: "):
            as_urls(bad)


def test_a_dial_that_keeps_failing_says_why_in_the_log_at_doubling_rounds(caplog):
    import logging

    from client.connection import Backoff, ClientError, open_patiently
    from proto.messages import PROTOCOL_VERSION, Hello

    hello = Hello(protocol=PROTOCOL_VERSION, scene="demo", viewport=[64, 64])
    with caplog.at_level(logging.WARNING, logger="walkstream.client"):
        with pytest.raises(ClientError, match="within"):
            open_patiently(["ws://127.0.0.1:1/ws"], hello, 0.2, 0.6, wait_unreachable=True,
                           backoff=Backoff(base=0.01, cap=0.02, random=lambda: 1.0))
    rounds = [r.getMessage() for r in caplog.records if "no server welcomed" in r.getMessage()]
    assert rounds and "127.0.0.1:1" in rounds[0]
    numbers = [int(m.split("round ")[1].split(",")[0]) for m in rounds]
    assert all(n & (n - 1) == 0 for n in numbers)  # 1, 2, 4, …: a long outage is not a flood
