"""The fleet page: ``/fleet.json``'s data as one server-rendered HTML page, with inline SVG sparklines.

No scripts and no front-end build: the page reloads itself (``<meta http-equiv=refresh>``), every text
that came from a client is escaped (``html.escape``), and each kiosk's frame times are drawn as an SVG
polyline. Marks a reader (or a test) looks for: ``STALE`` (class ``mark stale``) on a kiosk whose frames
stopped advancing, ``DISCONNECTED`` on one whose session ended, ``DUPLICATE`` on an id two sessions report.
"""

from __future__ import annotations

from html import escape

import numpy as np

__all__ = ["render", "sparkline"]

_STYLE = """
body { font: 14px/1.4 system-ui, sans-serif; margin: 1.5em; color: #222; }
h1 { font-size: 1.4em; margin: 0 0 .2em; } h2 { font-size: 1.1em; margin: 1.5em 0 .4em; }
table { border-collapse: collapse; } th, td { padding: .25em .6em; border-bottom: 1px solid #ddd; text-align: left; }
th { background: #f4f4f4; } td.num { text-align: right; font-variant-numeric: tabular-nums; }
tr.stale td { background: #fde8e8; } tr.gone td { color: #888; }
.mark { font-weight: bold; font-size: .8em; padding: 0 .35em; border-radius: 3px; margin-left: .3em; }
.mark.stale { background: #c62828; color: #fff; } .mark.gone { background: #777; color: #fff; }
.mark.duplicate { background: #ef6c00; color: #fff; }
svg.spark polyline { fill: none; stroke: #1565c0; stroke-width: 1.2; } svg.spark { background: #f8f8f8; }
.note { color: #666; }
"""


def sparkline(values, width: int = 160, height: int = 28, css: str = "spark") -> str:
    """An inline SVG polyline of ``values`` ((n,) float) left to right, scaled from 0 to their maximum."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    head = f'<svg class="{escape(css)}" width="{width}" height="{height}" viewBox="0 0 {width} {height}">'
    if v.size == 0:
        return head + "</svg>"
    top = float(v.max()) or 1.0
    x = np.linspace(1.0, width - 1.0, v.size) if v.size > 1 else np.array([width / 2.0])
    y = (height - 1.0) - (height - 2.0) * v / top
    points = " ".join(f"{a:.1f},{b:.1f}" for a, b in zip(x, y))
    title = f"{v.size} points, max {top * 1000:.1f} ms" if css == "spark" else f"{v.size} points"
    return f'{head}<title>{escape(title)}</title><polyline points="{points}"/></svg>'


def _bytes(n) -> str:
    if n is None:
        return "—"
    for unit, size in (("GiB", 1 << 30), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if n >= size:
            return f"{n / size:.1f} {unit}"
    return f"{int(n)} B"


def _age(s) -> str:
    return "—" if s is None else f"{s:.1f} s ago"


def _kiosk_row(k: dict) -> str:
    marks = []
    if k["stale"]:
        marks.append('<span class="mark stale" title="frames have not advanced for more than 2 heartbeat '
                     'intervals">STALE</span>')
    if not k["connected"]:
        marks.append('<span class="mark gone">DISCONNECTED</span>')
    if k["duplicate"]:
        marks.append('<span class="mark duplicate" title="more than one session reports this id">DUPLICATE</span>')
    classes = " ".join(["kiosk"] + (["stale"] if k["stale"] else []) + ([] if k["connected"] else ["gone"]))
    stop = "" if k["stop"] < 0 else f" · stop {k['stop']}"
    cells = [
        f'<td class="id">{escape(k["kiosk"])}</td>',
        f'<td class="state">{escape(k["state"])}{"".join(marks)}</td>',
        f'<td class="tour">{escape(k["tour"] or "—")}{stop}</td>',
        f'<td class="num fps">{k["fps"]:.1f}</td>',
        f'<td class="num p95">{k["frame_p95"] * 1000:.1f} ms</td>',
        f'<td class="frames">{sparkline(k["frame_times"] or k["frame_p95_history"])}</td>',
        f'<td class="num rss">{_bytes(k["rss"])}</td>',
        f'<td class="rss-trend">{sparkline(k["rss_history"], 80, 28, "spark rss")}</td>',
        f'<td class="num gpu">{_bytes(k["gpu_memory"])}</td>',
        f'<td class="num cache">{_bytes(k["cache_bytes"])}</td>',
        f'<td class="num reconnects">{k["reconnects"]}</td>',
        f'<td class="num frames-drawn">{k["frames"]}</td>',
        f'<td class="heard">{_age(k["heard_s"])}</td>',
        f'<td class="session">{escape(k["session"][:12])}</td>',
        f'<td class="worker">{escape(str(k.get("worker", "")))}</td>',
    ]
    return f'<tr class="{classes}" data-kiosk="{escape(k["kiosk"])}">{"".join(cells)}</tr>'


def _session_row(s: dict) -> str:
    cells = [escape(str(s.get("session", ""))), escape(str(s.get("kiosk") or "—")), escape(str(s.get("scene", ""))),
             escape(str(s.get("state", "")))]
    nums = [str(s.get("frames", 0)), str(s.get("selections", 0)), f"{s.get('connected_s', 0):.0f} s",
            f"{s.get('idle_s', 0):.1f} s", escape(str(s.get("worker", "")))]
    return ("<tr class=\"session\">" + "".join(f"<td>{c}</td>" for c in cells)
            + "".join(f'<td class="num">{c}</td>' for c in nums) + "</tr>")


def render(data: dict, replica: str, refresh: int = 3) -> str:
    """The page for ``data`` (``{"kiosks": [...], "sessions": [...]}`` as ``server.fleet.merge`` gives it)."""
    kiosks, sessions = data.get("kiosks", []), data.get("sessions", [])
    stale = sum(1 for k in kiosks if k["stale"])
    head = ["kiosk", "state", "tour · stop", "fps", "frame p95", "frame times", "RSS", "RSS trend", "GPU memory",
            "cache", "reconnects", "frames", "last heard", "session", "worker"]
    k_rows = "".join(_kiosk_row(k) for k in kiosks) or (
        f'<tr><td colspan="{len(head)}" class="note">no kiosk has reported yet</td></tr>')
    s_head = ["session", "kiosk", "scene", "state", "frames", "selections", "connected", "idle", "worker"]
    s_rows = "".join(_session_row(s) for s in sessions) or (
        f'<tr><td colspan="{len(s_head)}" class="note">no live session</td></tr>')
    return (
        "<!doctype html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
        f"<meta http-equiv=\"refresh\" content=\"{int(refresh)}\">"
        f"<title>walkstream fleet · {escape(replica)}</title><style>{_STYLE}</style></head><body>"
        f"<h1>Fleet of {escape(replica)}</h1>"
        f"<p class=\"summary\">{len(kiosks)} kiosks, {stale} stale · {len(sessions)} live sessions · "
        f"this page reloads every {int(refresh)} s · the same as JSON: <a href=\"fleet.json\">fleet.json</a></p>"
        "<h2>Kiosks</h2><table id=\"kiosks\"><thead><tr>" + "".join(f"<th>{h}</th>" for h in head)
        + f"</tr></thead><tbody>{k_rows}</tbody></table>"
        "<h2>Live sessions</h2><table id=\"sessions\"><thead><tr>" + "".join(f"<th>{h}</th>" for h in s_head)
        + f"</tr></thead><tbody>{s_rows}</tbody></table>"
        "</body></html>\n"
    )
