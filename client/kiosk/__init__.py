"""The museum kiosk: a walkthrough that runs unattended from opening to closing.

``hours`` (opening hours, the closed screen, the nightly restart), ``watchdog``
(systemd readiness and watchdog, fed only while frames advance) and ``logs``
(logging under a size cap) are the unattended-operation parts the runner calls.
"""
