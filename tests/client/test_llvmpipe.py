"""One rasterizer thread for llvmpipe where the client may run on one core only."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from client.llvmpipe import VARIABLE, raster_threads

PROBE = """
import json, os, sys
os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
from client.renderer import Renderer
r = Renderer(64, 64)
left = os.environ.get("LP_NUM_THREADS")
names = [open(f"/proc/self/task/{t}/comm").read().strip() for t in os.listdir("/proc/self/task")]
print(json.dumps({"left": left, "threads": [n for n in names if n.startswith("llvmpipe")]}))
"""


def _probe(**env) -> dict:
    environ = {k: v for k, v in os.environ.items() if k != VARIABLE} | env
    done = subprocess.run([sys.executable, "-c", PROBE], capture_output=True, text=True, env=environ, timeout=120,
                          cwd=os.path.dirname(os.path.dirname(os.path.dirname(__file__))))
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="no CPU affinity on this platform")
def test_a_renderer_on_one_core_rasterizes_in_a_thread_of_its_own():
    got = _probe()
    # one rasterizer thread, and the variable gone again: processes started later are not held to one
    assert got["left"] is None and got["threads"] == ["llvmpipe-0"], got


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="no CPU affinity on this platform")
def test_a_count_the_user_chose_is_kept():
    got = _probe(LP_NUM_THREADS="0")
    assert got["left"] == "0" and got["threads"] == [], got


def test_more_than_one_core_is_left_to_llvmpipe():
    environ: dict = {}
    with raster_threads(environ, cores={0, 1}) as value:
        assert value is None and environ == {}
    with raster_threads(environ, cores={3}) as value:
        assert value == "1" and environ == {VARIABLE: "1"}
    assert environ == {}
    with raster_threads({VARIABLE: "4"}, cores={3}) as value:
        assert value == "4"


def test_the_variable_is_lifted_when_the_context_fails():
    environ: dict = {}
    with pytest.raises(RuntimeError):
        with raster_threads(environ, cores={2}):
            raise RuntimeError("no context")
    assert environ == {}
