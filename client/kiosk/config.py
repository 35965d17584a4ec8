"""The kiosk's one config file (TOML): read, validated strictly, every error naming its key.

Sections: ``[kiosk]`` (id, server URLs, scene, viewport, languages, caption type, heartbeat, cache, logs),
``[navigation]`` (what a visitor drives: walk or fly, eye height, speed and turn caps, bounds), ``[idle]``
(the idle time and the countdown back to the attract loop), ``[schedule]`` (open hours, restart time),
``[attract]`` (the playlist of tours) and ``[[tours]]`` (stops inline, or from a ``file`` as
``walkstream client --record-tour`` writes it, TOML or JSON, relative to the config's folder).

Every section and key is checked; unknown keys are refused (a misspelt key must not silently fall back
to a default on a machine nobody watches). An error is one line naming the file and the key path::

    kiosk.toml: idle.countdown_s: must be at least 20 (WCAG 2.2.1)

The idle minimums (``idle_s`` ≥ 30, ``countdown_s`` ≥ 20, WCAG 2.2.1's "at least 20 seconds" to answer a
timeout warning) hold unless ``kiosk.test_mode = true`` says the file is a test's, never a public kiosk's.
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from proto.messages import Navigation
from ..connection import ClientError, check_url

__all__ = ["ConfigError", "KioskConfig", "StopConfig", "TourConfig", "load_config", "load_stops",
           "DEFAULT_FONT", "IDLE_MIN_S", "COUNTDOWN_MIN_S"]

#: The caption font when ``kiosk.font`` is "" (Debian's fonts-dejavu-core).
DEFAULT_FONT = "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf"
#: ``idle.idle_s`` at least this (a visitor pausing to read is not gone).
IDLE_MIN_S = 30.0
#: ``idle.countdown_s`` at least this: WCAG 2.2.1 (Timing Adjustable) gives at least 20 s to answer.
COUNTDOWN_MIN_S = 20.0
#: What ``kiosk.test_mode`` still requires of both (a test's kiosk must still count down).
TEST_MIN_S = 0.5

_HHMM = r"^([01][0-9]|2[0-3]):[0-5][0-9]$"
_NAME = r"^[A-Za-z0-9_.\-]+$"
Vec3 = Annotated[list[Annotated[float, Field(ge=-1e7, le=1e7)]], Field(min_length=3, max_length=3)]


class ConfigError(ValueError):
    """The config cannot be used; ``str()`` is one line: ``file: key.path: what is wrong``."""


class _Strict(BaseModel):
    model_config = ConfigDict(strict=True, extra="forbid", allow_inf_nan=False, frozen=True)


def _length(v: list[float]) -> float:
    return float(np.linalg.norm(np.asarray(v, np.float64)))


class StopConfig(_Strict):
    """One stop of a tour: where the camera stands, where it looks, how long, and what the caption says."""

    eye: Vec3
    forward: Vec3 | None = None
    look_at: Vec3 | None = None
    up: Vec3 = [0.0, 0.0, 1.0]
    dwell_s: Annotated[float, Field(ge=0.0, le=3600.0)] = 6.0
    caption: dict[Annotated[str, Field(pattern=r"^[a-z]{2,3}(-[A-Za-z0-9]{2,8})?$")],
                  Annotated[str, Field(max_length=2000)]] = {}

    @model_validator(mode="after")
    def _view(self) -> "StopConfig":
        if (self.forward is None) == (self.look_at is None):
            raise ValueError("give exactly one of forward and look_at")
        f = self.direction
        if _length(f.tolist()) < 1e-9:
            raise ValueError("forward is zero (or look_at is the eye itself)")
        if _length(self.up) < 1e-9 or _length(np.cross(f, self.up).tolist()) < 1e-6 * _length(self.up):
            raise ValueError("up must be a non-zero vector not parallel to the view direction")
        return self

    @property
    def direction(self) -> np.ndarray:
        """(3,) float64 unit view direction."""
        f = np.asarray(self.forward if self.forward is not None else np.subtract(self.look_at, self.eye), np.float64)
        n = np.linalg.norm(f)
        return f / n if n > 0 else f


class _StopFile(_Strict):
    """What ``walkstream client --record-tour`` writes, and a tour's ``file`` holds."""

    stops: Annotated[list[StopConfig], Field(min_length=1, max_length=1000)]


class TourConfig(_Strict):
    name: Annotated[str, Field(min_length=1, max_length=64, pattern=_NAME)]
    mode: Literal["fly", "walk"] = "fly"
    speed: Annotated[float, Field(gt=0.0, le=100.0)] = 3.0
    turn: Annotated[float, Field(gt=0.0, le=720.0)] = 45.0
    file: str = ""
    stops: Annotated[list[StopConfig], Field(max_length=1000)] = []

    @model_validator(mode="after")
    def _one_source(self) -> "TourConfig":
        if bool(self.file) == bool(self.stops):
            raise ValueError("give the stops inline ([[tours.stops]]) or in a file (file = ...), one of the two")
        return self


class KioskSection(_Strict):
    id: Annotated[str, Field(min_length=1, max_length=64, pattern=_NAME)]
    servers: Annotated[list[str], Field(min_length=1, max_length=16)]
    scene: Annotated[str, Field(min_length=1, max_length=128, pattern=_NAME)]
    viewport: Annotated[list[Annotated[int, Field(ge=16, le=16384)]], Field(min_length=2, max_length=2)] = [1280, 720]
    fullscreen: bool = True
    target_ms: Annotated[float, Field(ge=1.0, le=2000.0)] = 50.0
    languages: Annotated[list[Annotated[str, Field(pattern=r"^[a-z]{2,3}(-[A-Za-z0-9]{2,8})?$")]],
                         Field(min_length=1, max_length=32)] = ["en"]
    font: str = ""
    caption_px: Annotated[int, Field(ge=12, le=300)] = 40
    sky: bool = True
    heartbeat_s: Annotated[float, Field(ge=0.5, le=600.0)] = 5.0
    cache_mb: Annotated[int, Field(ge=1, le=1 << 20)] = 256
    log_file: str = ""
    log_max_mb: Annotated[float, Field(gt=0.0, le=1 << 20)] = 10.0
    log_backups: Annotated[int, Field(ge=0, le=100)] = 3
    #: The file belongs to a test: the idle minimums are lowered to ``TEST_MIN_S`` (never on a public kiosk).
    test_mode: bool = False

    @field_validator("servers")
    @classmethod
    def _urls(cls, v: list[str]) -> list[str]:
        for i, url in enumerate(v):
            try:
                check_url(url)
            except ClientError as exc:
                raise ValueError(f"[{i}]: {exc}") from None
        return v

    @field_validator("languages")
    @classmethod
    def _unique(cls, v: list[str]) -> list[str]:
        if len(set(v)) != len(v):
            raise ValueError("a language is listed twice")
        return v


class NavigationSection(_Strict):
    mode: Literal["walk", "fly"] = "walk"
    eye_height: Annotated[float, Field(gt=0.0, le=100.0)] = 1.7
    max_speed: Annotated[float, Field(gt=0.0, le=1.0e4)] = 2.0
    max_turn: Annotated[float, Field(gt=0.0, le=3600.0)] = 60.0
    bounds: Annotated[list[Vec3], Field(max_length=2)] = []

    @field_validator("bounds")
    @classmethod
    def _box(cls, v: list[list[float]]) -> list[list[float]]:
        if v and (len(v) != 2 or any(lo >= hi for lo, hi in zip(*v))):
            raise ValueError("must be [] (the scene's bounds) or [[x0, y0, z0], [x1, y1, z1]] with x0 < x1, "
                             "y0 < y1, z0 < z1")
        return v


class IdleSection(_Strict):
    idle_s: Annotated[float, Field(gt=0.0, le=86400.0)] = 90.0
    countdown_s: Annotated[float, Field(gt=0.0, le=3600.0)] = 20.0


class ScheduleSection(_Strict):
    open: Annotated[str, Field(pattern=_HHMM)] = "00:00"
    close: Annotated[str, Field(pattern=_HHMM)] = "00:00"
    closed: Literal["dim", "black"] = "dim"
    restart_at: Annotated[str, Field(pattern=r"^$|" + _HHMM)] = ""


class AttractSection(_Strict):
    playlist: Annotated[list[Annotated[str, Field(min_length=1, max_length=64)]], Field(min_length=1)]


class KioskConfig(_Strict):
    """The whole file, validated; ``tours`` hold their stops (a ``file`` already read)."""

    kiosk: KioskSection
    navigation: NavigationSection = NavigationSection()
    idle: IdleSection = IdleSection()
    schedule: ScheduleSection = ScheduleSection()
    attract: AttractSection
    tours: Annotated[list[TourConfig], Field(min_length=1, max_length=256)]

    @property
    def font(self) -> str:
        """The caption font's path."""
        return self.kiosk.font or DEFAULT_FONT

    @property
    def playlist(self) -> list[TourConfig]:
        """The attract loop's tours, in order."""
        by_name = {t.name: t for t in self.tours}
        return [by_name[name] for name in self.attract.playlist]

    def navigation_message(self) -> Navigation:
        """What the hello says of the visitor's degrees of freedom."""
        n = self.navigation
        return Navigation(mode=n.mode, eye_height=n.eye_height, bounds=n.bounds or None)


# --------------------------------------------------------------------------- errors


def _where(loc: tuple) -> str:
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


def _what(err: dict) -> str:
    kind, ctx, got = err["type"], err.get("ctx", {}), err.get("input")
    if kind == "missing":
        return "missing (required)"
    if kind == "extra_forbidden":
        return "unknown key"
    if kind == "greater_than_equal":
        return f"must be at least {ctx['ge']}"
    if kind == "greater_than":
        return f"must be more than {ctx['gt']}"
    if kind == "less_than_equal":
        return f"must be at most {ctx['le']}"
    if kind == "less_than":
        return f"must be less than {ctx['lt']}"
    if kind in ("too_short", "string_too_short"):
        return f"needs at least {ctx.get('min_length')} {'items' if kind == 'too_short' else 'characters'}"
    if kind in ("too_long", "string_too_long"):
        return f"takes at most {ctx.get('max_length')} {'items' if kind == 'too_long' else 'characters'}"
    if kind == "string_pattern_mismatch":
        return f"{got!r} does not match {ctx['pattern']}"
    if kind == "literal_error":
        return f"must be one of {ctx['expected']}, got {got!r}"
    if kind.endswith("_type") or kind.endswith("_parsing"):
        want = kind.split("_")[0].replace("model", "table").replace("dict", "table")
        return f"must be a {want}, got {type(got).__name__} {got!r}"[:200]
    if kind == "value_error":
        return str(err["msg"]).removeprefix("Value error, ")
    return str(err["msg"])


def _one_line(name: str, exc: ValidationError, prefix: tuple = ()) -> ConfigError:
    errors = exc.errors(include_url=False)
    first = errors[0]
    loc = prefix + tuple(first["loc"])
    what = _what(first)
    if what.startswith("["):  # a list validator naming its item: servers[1]: ...
        loc, what = loc + (int(what[1:what.index("]")]),), what[what.index("]:") + 2:].lstrip()
    more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
    return ConfigError(f"{name}: {_where(loc) or '(top level)'}: {what}{more}")


# --------------------------------------------------------------------------- reading


def _read(path: Path, label: str) -> dict:
    """A TOML or JSON file (by suffix; TOML otherwise) as a dict, or ConfigError naming it."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{label}: cannot read it: {exc.strerror if isinstance(exc, OSError) else exc}") from None
    try:
        data = json.loads(text) if path.suffix.lower() == ".json" else tomllib.loads(text)
    except (tomllib.TOMLDecodeError, json.JSONDecodeError) as exc:
        raise ConfigError(f"{label}: not valid {'JSON' if path.suffix.lower() == '.json' else 'TOML'}: {exc}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{label}: the top level must be a table")
    return data


def load_stops(path: str | Path) -> list[StopConfig]:
    """The stops of a tour file (``stops = [...]``, TOML or JSON, as ``--record-tour`` writes it)."""
    path = Path(path)
    try:
        return list(_StopFile.model_validate(_read(path, path.name)).stops)
    except ValidationError as exc:
        raise _one_line(path.name, exc) from None


def load_config(path: str | Path) -> KioskConfig:
    """Read and validate the kiosk config at ``path``; raises ``ConfigError`` (one line) on any problem."""
    path = Path(path)
    name = path.name
    try:
        config = KioskConfig.model_validate(_read(path, name))
    except ValidationError as exc:
        raise _one_line(name, exc) from None
    problems: list[str] = []
    k, idle = config.kiosk, config.idle
    floor_idle, floor_count = (TEST_MIN_S, TEST_MIN_S) if k.test_mode else (IDLE_MIN_S, COUNTDOWN_MIN_S)
    if idle.idle_s < floor_idle:
        problems.append(f"idle.idle_s: must be at least {floor_idle:g}")
    if idle.countdown_s < floor_count:
        problems.append(f"idle.countdown_s: must be at least {floor_count:g} (WCAG 2.2.1)")
    font = Path(config.font)
    if not font.is_file():
        problems.append(f"kiosk.font: no font file at {str(font)!r}"
                        + (" (apt-get install fonts-dejavu-core)" if not k.font else ""))
    names = [t.name for t in config.tours]
    for i, n in enumerate(names):
        if n in names[:i]:
            problems.append(f"tours[{i}].name: {n!r} names an earlier tour too")
    for i, n in enumerate(config.attract.playlist):
        if n not in names:
            problems.append(f"attract.playlist[{i}]: no tour named {n!r} (tours: {', '.join(names)})")
    tours = []
    for i, tour in enumerate(config.tours):
        if tour.file:
            file = Path(tour.file)
            file = file if file.is_absolute() else path.parent / file
            try:
                tour = tour.model_copy(update={"stops": load_stops(file)})
            except ConfigError as exc:
                problems.append(f"tours[{i}].file: {exc}")
        for j, stop in enumerate(tour.stops):
            for lang in stop.caption:
                if lang not in k.languages:
                    problems.append(f"tours[{i}].stops[{j}].caption.{lang}: not one of kiosk.languages "
                                    f"({', '.join(k.languages)})")
        tours.append(tour)
    if problems:
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        raise ConfigError(f"{name}: {problems[0]}{more}")
    return config.model_copy(update={"tours": tours})
