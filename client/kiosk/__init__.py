"""The museum kiosk: one config file, authored tours as an attract loop, constrained navigation, captions.

``walkstream kiosk CONFIG.toml`` runs ``client.kiosk.run.run_kiosk``: the same client as ``walkstream client``
(frame loop, governor, redialling link), its camera driven by ``client.kiosk.director.Director`` — the attract
loop (``client.kiosk.stops``) while nobody touches it, the visitor's constrained walk or flight
(``client.kiosk.walking``) while someone does, and back after the idle countdown (``client.kiosk.attract``).

``hours`` (opening hours, the closed screen, the nightly restart), ``watchdog``
(systemd readiness and watchdog, fed only while frames advance) and ``logs``
(logging under a size cap) are the unattended-operation parts the runner calls.
"""
