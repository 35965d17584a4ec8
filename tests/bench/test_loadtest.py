"""The load generator: its simulated client agrees with the real client's cache and the wire schema, its
latency quantiles with the histogram they come from, and a short real run against a spawned server."""

from __future__ import annotations

import http.server
import json
import math
import subprocess
import sys
import threading
from pathlib import Path

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bench.loadtest.client import ClientConfig, HeldSet, RendererModel, SimulatedClient, payload_counts, unframe
from bench.loadtest.metrics import histogram_quantile, merge, parse_metrics, proc_cpu, tree_cpu
from bench.loadtest.run import LoadtestError, run_loadtest
from client.cache import ResidentCache
from proto.codec import decode_client, encode
from proto.geometry import encode_geometry
from proto.manifest import digest
from proto.messages import Ack, Camera, Delta, FrameReport, Pong, RepresentationAdd
from proto.points import encode_instances

ROOT = Path(__file__).resolve().parents[2]


def _mesh(n: int) -> bytes:
    """A fan of n triangles (n + 2 vertices)."""
    a = np.linspace(0, np.pi, n + 1)
    pos = np.concatenate([[[0.0, 0.0, 0.0]], np.stack([np.cos(a), np.sin(a), a * 0.1], 1)])
    faces = np.stack([np.zeros(n, int), np.arange(1, n + 1), np.arange(2, n + 2)], 1)
    return encode_geometry(pos, faces)


PAYLOADS = [_mesh(n) for n in (1, 3, 8, 20)]


def _config(**kw) -> ClientConfig:
    base = dict(url="ws://127.0.0.1:1/ws", http="http://127.0.0.1:1", scene="demo", rate=10.0, target=0.05,
                algorithms=("flat", "lit"), model=RendererModel(), seed=0)
    return ClientConfig(**{**base, **kw})


# --------------------------------------------------------------------------- the simulated cache


deltas = st.lists(
    st.tuples(
        st.lists(st.tuples(st.integers(0, 40), st.integers(0, len(PAYLOADS) - 1)), max_size=8),  # adds
        st.lists(st.integers(0, 40), max_size=6),  # drops
    ),
    min_size=1, max_size=12,
)


@settings(max_examples=60, deadline=None)
@given(deltas)
def test_acks_match_the_real_client_cache(seq):
    """What a simulated client acks (held, held_bytes, digest) after every delta equals what client.cache acks."""
    real = ResidentCache()
    sim = SimulatedClient(0, 1, _config())
    for i, (adds, drops) in enumerate(seq):
        delta = Delta(seq=i + 1, t0=0.0, t1=0.5, drop=drops, selection=[r for r, _ in adds],
                      add=[RepresentationAdd(rep=r, object=r, level=0, geometry=PAYLOADS[p]) for r, p in adds])
        real.apply(delta)
        ack = sim.apply_delta(unframe(encode(delta)), t=1.0)
        assert (ack["held"], ack["held_bytes"], ack["digest"]) == (real.held, real.held_bytes, real.digest)
        assert ack["digest"] == digest(sim.held.ids())
        assert set(sim.held.ids().tolist()) == set(real.resident)


def test_payload_counts_read_the_header_only(demo_store):
    """Vertex and face counts from the payload's map equal the store's, for every representation of a scene;
    a tree group's payload gives its instance count."""
    from server.scene.store import SceneStore

    with SceneStore.open(demo_store) as store:
        idx = store.index
        reps = list(range(idx.n_representations))
        counts = np.array([payload_counts(b) for b in store.geometries(reps)])
        assert np.array_equal(counts[:, 0], idx.rep_vertices)
        assert np.array_equal(counts[:, 1], idx.rep_faces)
    trees = encode_instances(np.array([0, 1, 1]), np.tile(np.eye(4), (3, 1, 1)))
    assert payload_counts(trees) == (0, 0, 3)
    assert payload_counts(b"\x00garbage") == (0, 0, 0)


def test_hand_built_messages_pass_the_servers_decoder():
    """Camera, frame report, ack and pong maps built without pydantic are valid protocol-4 client messages,
    and the frame report's totals and per-algorithm terms agree with the renderer model."""
    sim = SimulatedClient(3, 8, _config())
    adds = [RepresentationAdd(rep=r, object=r, level=0, geometry=PAYLOADS[r % 4]) for r in range(6)]
    delta = Delta(seq=1, t0=0.0, t1=0.5, add=adds, selection=[0, 2, 4, 5], algorithm=[0, 1, 0, 1], reset=True)
    ack = sim.apply_delta(unframe(encode(delta)), t=0.2)
    assert isinstance(decode_client(msgpack.packb(ack)), Ack)
    report, ft = sim.frame_report(7, 0.3, noise=1.0)
    msg = decode_client(msgpack.packb(report))
    assert isinstance(msg, FrameReport) and msg.selection == 1
    faces = [payload_counts(PAYLOADS[r % 4])[1] for r in (0, 2, 4, 5)]
    verts = [payload_counts(PAYLOADS[r % 4])[0] for r in (0, 2, 4, 5)]
    assert msg.triangles == sum(faces) and msg.vertices == sum(verts) and msg.draws == 4
    assert msg.terms.triangles[:2] == [faces[0] + faces[2], faces[1] + faces[3]]
    assert msg.terms.draws == [2, 2, 0]
    assert ft == pytest.approx(RendererModel().overhead + RendererModel().c_vertex * sum(verts))
    # A later delta's selection is drawn only from its t0.
    sim.apply_delta(unframe(encode(Delta(seq=2, t0=1.0, t1=1.5, start=0.5, selection=[1]))), t=0.6)
    assert sim.frame_report(8, 0.9, 1.0)[0]["selection"] == 1
    assert sim.frame_report(9, 1.0, 1.0)[0]["vertices"] == payload_counts(PAYLOADS[1])[0]
    cam = {"type": "camera", "t": 0.3, "eye": [1.0, 2.0, 3.0], "forward": [0.0, 1.0, 0.0], "up": [0.0, 0.0, 1.0]}
    assert isinstance(decode_client(msgpack.packb(cam)), Camera)
    assert isinstance(decode_client(msgpack.packb({"type": "pong", "id": 3, "sent": 12.5, "t": 0.4})), Pong)


# --------------------------------------------------------------------------- latency from the histogram


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(1e-4, 3.0), min_size=1, max_size=200), st.sampled_from([0.5, 0.9, 0.99]))
def test_quantile_lies_in_the_bucket_of_the_true_quantile(samples, q):
    """Read through prometheus_client's own exposition, the interpolated quantile lands in the bucket that holds
    the samples' q-quantile (or at the largest bound when that is +Inf)."""
    from prometheus_client import CollectorRegistry, Histogram, generate_latest

    from server.metrics import LATENCY_BUCKETS

    reg = CollectorRegistry()
    h = Histogram("walkstream_selection_seconds", "x", buckets=LATENCY_BUCKETS, registry=reg)
    for s in samples:
        h.observe(s)
    scrape = parse_metrics(generate_latest(reg).decode())
    le, cum = scrape.hist["walkstream_selection_seconds"]
    assert cum[-1] == len(samples)
    got = histogram_quantile(le, cum, q)
    rank = math.ceil(q * len(samples))  # the sample the quantile's rank lands on
    true = sorted(samples)[rank - 1]
    bounds = (0.0,) + LATENCY_BUCKETS + (math.inf,)
    i = int(np.searchsorted(LATENCY_BUCKETS, true, side="left"))  # bucket (bounds[i], bounds[i + 1]]
    if i == len(LATENCY_BUCKETS):
        assert got == LATENCY_BUCKETS[-1]
    else:
        assert bounds[i] <= got <= bounds[i + 1]


def test_quantile_edge_cases():
    le = np.array([0.01, 0.1, math.inf])
    assert math.isnan(histogram_quantile(le, np.zeros(3), 0.5))
    assert histogram_quantile(le, np.array([0.0, 10.0, 10.0]), 0.5) == pytest.approx(0.055)
    assert histogram_quantile(le, np.array([10.0, 10.0, 10.0]), 0.99) == pytest.approx(0.0099)


# --------------------------------------------------------------------------- real runs


def test_short_real_run(demo_store):
    """4 clients for 6 s against a spawned server: every session opens, deltas reach every client, the acks
    match the server's mirror, nothing goes wrong, and every figure is there."""
    s = run_loadtest(clients=4, duration=6.0, ramp=1.0, stores=[demo_store], reference=1.5, seed=1)
    assert s.sessions_opened == 4 and s.connected_at_end == 4
    assert s.clients_with_deltas == 4 and s.min_deltas_per_client >= 2
    assert s.acks >= s.min_deltas_per_client * 4 and s.pongs >= 4
    assert s.errors == {} and s.server_errors == {}
    assert s.mirror_checks is not None, "the spawned server's /sessions should answer its admin token"
    assert s.mirror_checks > 0 and s.mirror_mismatch == 0 and s.resyncs == 0
    for v in (s.selection_p50_ms, s.selection_p99_ms, s.selections_per_s, s.bytes_per_s, s.server_cpu_s,
              s.sessions_per_core, s.server_cpu_per_session_s, s.frame_p95_ms):
        assert v is not None and math.isfinite(v) and v > 0
    assert s.selection_p50_ms <= s.selection_p99_ms
    assert s.selections_measured > 0 and s.polls_per_tick is not None and s.polls_per_tick >= 1.0
    assert s.selections_due_share is not None and s.selections_due_share > 0
    assert s.server_pid is not None and s.scene
    r = s.reference
    assert r is not None and r.clients == 1 and r.sessions_opened == 1 and r.errors == {}
    assert s.cpu_per_session_ratio is not None and s.cpu_per_session_ratio > 0
    json.dumps(s.as_dict())  # every figure is JSON


def test_cli_json(demo_store):
    """``walkstream loadtest --json`` prints one parseable JSON object on stdout with the summary's keys."""
    out = subprocess.run(
        [sys.executable, "-m", "walkstream", "loadtest", "--store", str(demo_store), "--clients", "2",
         "--duration", "2.5", "--ramp", "0.5", "--reference", "0", "--workers", "1", "--workers", "2",
         "--no-coherent", "--json"],
        cwd=ROOT, capture_output=True, text=True, timeout=240,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    summary = json.loads(out.stdout.strip().splitlines()[-1])
    for key in ("clients", "sessions_opened", "selections_per_s", "selection_p50_ms", "selection_p99_ms",
                "delta_interarrival_p99_ms", "bytes_per_s", "server_cpu_per_session_s", "sessions_per_core",
                "errors", "frame_p95_ms", "frame_target_ms", "reference", "goal_met", "selections_due_share",
                "generator_cpu_per_session_s", "generator_cores", "server_cores", "runs", "goals"):
        assert key in summary
    assert summary["clients"] == 2 and summary["sessions_opened"] == 2 and summary["errors"] == {}
    # A run per worker count, each with its own server of that many processes, and the scaling between them.
    assert [r["workers"] for r in summary["runs"]] == [1, 2]
    assert all(r["server_cpu_per_session_s"] > 0 and r["sessions_opened"] == 2 for r in summary["runs"])
    goals = {(g["goal"], g.get("workers")): g for g in summary["goals"]}
    assert set(goals) == {("sessions_per_core", 1), ("sessions_per_core", 2), ("scaling", 2)}
    assert all(isinstance(g["goal_met"], bool) for g in goals.values())
    assert summary["goal_met"] == all(g["goal_met"] for g in goals.values())
    assert "walkstream loadtest" in out.stderr  # the live table and the summary go to stderr
    assert "goal scaling (2 workers)" in out.stderr


def test_a_replica_cpu_is_read_finer_than_a_clock_tick():
    """A one-client server spends about a clock tick's CPU a second: its CPU is read to the scheduler's
    nanoseconds, not rounded down to whole ticks. The child stops halfway between two ticks, where ticks would
    read 5 ms short of what it spent."""
    code = ("import sys, time\n"
            "while time.process_time() % 0.01 < 0.005 or time.process_time() < 0.05: pass\n"
            "print(time.process_time(), flush=True); sys.stdin.readline()")
    proc = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        spent = float(proc.stdout.readline())
        assert spent <= tree_cpu(proc.pid) <= spent + 0.004
    finally:
        proc.kill()
        proc.wait()


def test_a_replica_cpu_is_its_processes_together():
    """The CPU of a process tree counts every process below the root, and the children it already reaped."""
    code = ("import subprocess, sys, time\n"
            "burn = 'import time\\nt = time.process_time()\\nwhile time.process_time() - t < 0.6: pass'\n"
            "subprocess.run([sys.executable, '-c', burn])\n"  # reaped: counted in the parent's children time
            "p = subprocess.Popen([sys.executable, '-c', burn + '\\nprint(1, flush=True)\\ntime.sleep(30)'],\n"
            "                     stdout=subprocess.PIPE)\n"
            "p.stdout.readline(); print('ready', flush=True); time.sleep(30)")  # the live child has burnt its share
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        assert 1.2 <= tree_cpu(proc.pid) <= 3.0
        assert proc_cpu(proc.pid) < 0.6
    finally:
        proc.kill()
        proc.wait()
    assert tree_cpu(proc.pid) is None


def test_scrapes_of_several_servers_add_up():
    text = ("# TYPE walkstream_cpu_seconds gauge\nwalkstream_cpu_seconds 2.5\n"
            "# TYPE walkstream_selection_seconds histogram\n"
            'walkstream_selection_seconds_bucket{le="0.1"} 3.0\nwalkstream_selection_seconds_bucket{le="+Inf"} 4.0\n'
            "walkstream_selection_seconds_count 4.0\nwalkstream_selection_seconds_sum 0.5\n")
    both = merge([parse_metrics(text, 1.0), parse_metrics(text, 2.0)])
    assert both.values["walkstream_cpu_seconds"] == 5.0 and both.at == 2.0
    assert both.hist["walkstream_selection_seconds"][1].tolist() == [6.0, 8.0]


class _NoMetrics(http.server.BaseHTTPRequestHandler):
    def do_GET(self):  # noqa: N802
        self.send_error(404)

    def log_message(self, *args):
        pass


def test_a_server_without_metrics_is_refused_clearly():
    srv = http.server.ThreadingHTTPServer(("127.0.0.1", 0), _NoMetrics)
    thread = threading.Thread(target=srv.serve_forever, daemon=True)
    thread.start()
    try:
        with pytest.raises(LoadtestError, match="has no /metrics"):
            run_loadtest(url=f"ws://127.0.0.1:{srv.server_address[1]}/ws", clients=1, duration=1, reference=0)
    finally:
        srv.shutdown()
        srv.server_close()


def test_refusals_are_counted_by_code(demo_store):
    """Against a running server (``url``) that takes two sessions, four clients: two open, two are refused
    with ``busy``, and the summary says so (client side and the server's own count)."""
    from bench.demo import ServerProcess

    with ServerProcess([demo_store], extra=["--max-sessions", "2"]) as srv:
        s = run_loadtest(url=srv.url, clients=4, duration=2.0, ramp=0.0, reference=0,
                         admin_headers=srv.admin_headers)
    assert s.sessions_opened == 2 and s.connected_at_end == 2
    assert s.errors.get("busy") == 2
    assert s.server_errors.get("busy") == 2
    assert s.tau is None and s.server_pid is None  # the server is not ours
    assert s.mirror_checks is not None and s.mirror_mismatch == 0
    assert not s.goal_met
