"""The commented example config ``walkstream kiosk --example`` prints: the auditorium, a five-stop tour.

The scene is ``walkstream build auditorium`` (Funkhouser & Séquin's hall: stage with a piano and a lectern,
twenty rows of chairs rising to the back; z up, the stage at low y). Coordinates are the served scene's —
the store's, recentred on build: the hall spans x ∈ [−15, 15], y ∈ [−18, 18], the stage's front edge at
y = −10, the first row at y = −7. Every stop looks at something in it.
"""

from __future__ import annotations

__all__ = ["EXAMPLE"]

EXAMPLE = '''\
# walkstream kiosk config — `walkstream kiosk kiosk.toml` (check it: the kiosk refuses a bad file on start,
# naming the key). This one shows the auditorium: `walkstream build auditorium && walkstream serve auditorium.db`.

[kiosk]
id = "lobby-1"                        # this kiosk's name on the server's /fleet page
servers = ["ws://127.0.0.1:8765/ws"]  # tried in turn; the next one when the current one is lost
scene = "auditorium"
viewport = [1280, 720]                # the window's size when not fullscreen
fullscreen = true                     # false: a window of `viewport`
target_ms = 50.0                      # the frame time the server selects for
languages = ["en", "de"]              # captions' languages; the first is the default (restored when idle)
font = ""                             # a TTF file; "" = DejaVu Sans (Debian: fonts-dejavu-core)
caption_px = 40                       # caption type size in pixels: legible at arm's length
sky = true                            # the sky behind the scene; false = one plain colour
heartbeat_s = 5.0                     # how often the kiosk reports its health to the server
cache_mb = 256                        # the client cache's byte budget
log_file = ""                         # "" = stderr; else a file rotated at log_max_mb, log_backups kept
log_max_mb = 10
log_backups = 3

[navigation]                          # what a visitor drives when they touch the screen
mode = "walk"                         # walk (eye height above the walkable ground) | fly
eye_height = 1.7                      # metres
max_speed = 2.0                       # m/s
max_turn = 60.0                       # degrees/s
bounds = [[-14.5, -17.5, 0.2], [14.5, 17.5, 10.5]]  # the camera never leaves this box; [] = the scene's bounds

[idle]
idle_s = 90.0                         # this long without a touch → the countdown (at least 30)
countdown_s = 20.0                    # "Touch to continue", then the attract loop (at least 20: WCAG 2.2.1)

[schedule]
open = "00:00"                        # local time HH:MM; open == close: always open
close = "00:00"
closed = "dim"                        # outside the open hours: dim (darkened attract loop) | black
restart_at = ""                       # "HH:MM": the kiosk exits then with status 75 (systemd restarts it)

[attract]
playlist = ["highlights"]             # tours played in a loop while nobody touches the kiosk

[[tours]]
name = "highlights"
mode = "fly"                          # fly | walk (walk: the path keeps the eye height above the ground)
speed = 3.0                           # m/s between stops
turn = 45.0                           # degrees/s
# file = "highlights.toml"            # stops from a file instead (`walkstream client --window --record-tour`)

  [[tours.stops]]
  eye = [0.0, 16.5, 5.5]              # the back of the hall, high up (the scene's coordinates, metres)
  look_at = [0.0, -10.0, 1.0]         # or forward = [x, y, z]
  dwell_s = 8.0
  caption = { en = "The auditorium: 440 chairs facing the stage", de = "Der Saal: 440 Stühle vor der Bühne" }

  [[tours.stops]]
  eye = [-8.8, -8.1, 1.6]             # the front-left corner
  look_at = [2.0, -1.0, 0.6]
  dwell_s = 8.0
  caption = { en = "Twenty rows, each a step higher", de = "Zwanzig Reihen, jede eine Stufe höher" }

  [[tours.stops]]
  eye = [-3.0, -8.4, 2.6]             # in front of the stage
  look_at = [-3.0, -13.8, 1.7]
  dwell_s = 8.0
  caption = { en = "The grand piano", de = "Der Flügel" }

  [[tours.stops]]
  eye = [3.5, -8.4, 2.4]
  look_at = [3.5, -13.0, 1.7]
  dwell_s = 6.0
  caption = { en = "The lectern", de = "Das Rednerpult" }

  [[tours.stops]]
  eye = [0.0, 2.5, 3.3]               # the central aisle, row 10
  look_at = [-8.0, -4.0, 0.8]
  up = [0.0, 0.0, 1.0]
  dwell_s = 6.0
  caption = { en = "From the aisle: the seats up close", de = "Vom Mittelgang: die Sitze aus der Nähe" }
'''
