"""A hello that names a tour is welcomed with that tour; one the scene lacks is refused, naming those it has."""

from __future__ import annotations

from time import perf_counter

import pytest

from proto import PROTOCOL_VERSION
from proto.codec import decode_server, encode
from proto.messages import Error, Hello, Welcome
from server.scene.store import SceneStore
from server.scene.tour import named_tours
from server.session import Session, SessionState


@pytest.fixture()
def scenes(city_store, demo_store):
    stores = [SceneStore.open(city_store), SceneStore.open(demo_store)]
    yield {s.index.name: s for s in stores}
    for s in stores:
        s.close()


def _hello(scene: str, **kw) -> bytes:
    return encode(Hello(protocol=PROTOCOL_VERSION, scene=scene, viewport=[320, 180], **kw))


def _eyes(keys) -> list:
    return [list(k["eye"]) if isinstance(k, dict) else list(k.eye) for k in keys]


@pytest.mark.parametrize("tour", ["walk", "flyover", "orbit", None])
def test_the_welcome_carries_the_named_tour_and_starts_on_it(scenes, tour):
    s = Session(scenes, "s1", stopwatch=perf_counter)
    welcome = decode_server(encode(s.receive(_hello("city", tour=tour), now=0.0)[0]))
    assert isinstance(welcome, Welcome)
    index = scenes["city"].index
    keys = named_tours(index)[tour or "walk"]["keys"]  # the walk is the city's default tour
    assert _eyes(welcome.tour) == _eyes(keys)
    assert list(welcome.start.eye) == keys[0]["eye"] and list(welcome.start.forward) == keys[0]["forward"]


def test_an_unknown_tour_is_refused_naming_the_tours_there_are(scenes):
    s = Session(scenes, "s2", stopwatch=perf_counter)
    (err,) = s.receive(_hello("city", tour="funicular"), now=0.0)
    assert isinstance(err, Error) and err.code == "unknown_tour" and s.state is SessionState.AWAIT_HELLO
    assert "'funicular'" in err.message and "its tours: flyover, orbit, walk" in err.message
    (err,) = s.receive(_hello("demo", tour="walk"), now=0.0)  # the demo came with one tour: its own
    assert err.code == "unknown_tour" and "its tours: scene" in err.message
    welcome, _ = s.receive(_hello("demo", tour="scene"), now=0.0)
    assert isinstance(welcome, Welcome) and _eyes(welcome.tour) == _eyes(scenes["demo"].index.tour)
