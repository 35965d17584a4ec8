"""``walkstream loadtest``: many simulated clients against one server, and what it cost the server.

Each simulated client speaks protocol 4 like the real one (hello, camera poses
along the scene's tour, a frame report per frame, pongs at once, an ack with
``held``/``held_bytes``/``digest`` after every delta) but draws nothing: its
frame time comes from a renderer model (``RendererModel``) applied to the
vertex and face counts of what its selection draws. All clients share one
asyncio loop in this process, so the load generator must stay cheap next to
the server it measures (they share the machine's cores):

- outgoing messages are msgpack maps built by hand to match ``proto.messages``
  (no pydantic per message; the test checks them against the real decoder);
- incoming frames are unpacked with msgpack only; a payload's vertex and face
  counts are read from its map header, the geometry is never decoded;
- poses come from the tour in vectorised chunks, not one ``pose_at`` per frame.

The server's side of the story comes from its ``/metrics`` (Prometheus text):
the selection-latency histogram over the measured window and bytes out; the
server's CPU seconds are its processes' own — a started server's supervisor and
workers read from ``/proc``, another's ``walkstream_cpu_seconds``, summed over
the replicas ``--metrics`` names. ``goals`` runs one test per worker count and
reports the issue's goals with the scaling ratio between them. A one-client reference is
measured in the same run first, because a shared machine's absolute figures
drift; the ratios against it are what to read.
"""
