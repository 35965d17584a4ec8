"""An on-screen window for the client: glfw, a GL 3.3 core context, keys and mouse.

The renderer keeps drawing into its own offscreen framebuffer, so the timed
draw (and the cost model fitted to it) is the same with or without a window;
``present`` then blits that image to the window and swaps, outside the fence.
On a machine without a display, run under a virtual one:
``xvfb-run -a walkstream client --window``.

Keys (``--navigate fly`` or ``walk``; with ``tour`` only F, P and Escape act):

==========  ===========================================================
W A S D     move forward / left / back / right
Q / E       down / up (flying only: walking keeps its eye height)
mouse drag  look around (hold the left button)
arrows      turn and look up/down at the turn limit
Shift       move faster (×4 by default)
Tab         toggle fly ↔ walk where the camera is
F           toggle false colour (``Renderer.false_colour``)
P           write a screenshot of the window (walkstream-<time>.png)
M / Space   mark the current pose as a tour stop (with ``--record-tour``)
Escape      close the window (the session ends)
==========  ===========================================================

A click or tap (press and release within ``TAP_SLOP`` px) goes to the controller's ``tap(x, y)`` when it
has one (a kiosk's buttons), in framebuffer pixels, y down. A ``public`` window (a kiosk's) gives every
key to the controller: Escape, Tab, F and P do nothing there.

Turning is rate-limited (``Navigator.max_turn``) and movement capped
(``Navigator.max_speed``): the client announces both in its ``Hello``, and the
server's conservative camera counts on them.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any, Callable, Protocol

import numpy as np

from .llvmpipe import raster_threads

__all__ = ["Window", "WindowError", "KEY_NAMES", "TAP_SLOP"]

#: A press and release of the left button this close (px) is a tap, not a drag.
TAP_SLOP = 12.0

_DISPLAY_HINT = (
    "a window needs a display: set DISPLAY (or WAYLAND_DISPLAY), run under a virtual one with "
    "`xvfb-run -a walkstream client --window ...`, or drop --window to render headless"
)


class WindowError(RuntimeError):
    """No window could be opened: no display, no glfw, or no suitable GL context."""


class _Input(Protocol):
    def key(self, name: str, pressed: bool) -> bool: ...
    def look(self, dx: float, dy: float) -> None: ...


def _glfw() -> Any:
    try:
        import glfw
    except ImportError as exc:  # pragma: no cover - glfw is a dependency
        raise WindowError(f"the window needs the glfw package (pip install glfw): {exc}") from None
    return glfw


_errors: list[str] = []  # glfw reports failures through a callback, not return values
_windows = 0  # glfw is initialised while any window is open


def _on_glfw_error(code: int, description: bytes | str) -> None:
    text = description.decode(errors="replace") if isinstance(description, bytes) else str(description)
    _errors.append(f"{text} (glfw error {code:#x})")
    del _errors[:-8]


def _last_error(default: str) -> str:
    return _errors[-1] if _errors else default


def _key_names(glfw: Any) -> dict[int, str]:
    """glfw key codes → the names ``Navigator.key`` and ``Window.on_key`` take."""
    names = {getattr(glfw, f"KEY_{c.upper()}"): c for c in "wasdqefpm"}
    names.update({glfw.KEY_LEFT_SHIFT: "shift", glfw.KEY_RIGHT_SHIFT: "shift", glfw.KEY_TAB: "tab",
                  glfw.KEY_ESCAPE: "escape", glfw.KEY_LEFT: "left", glfw.KEY_RIGHT: "right",
                  glfw.KEY_UP: "up", glfw.KEY_DOWN: "down", glfw.KEY_SPACE: "space"})
    return names


#: Every key name the window reacts to.
KEY_NAMES = ("w", "a", "s", "d", "q", "e", "shift", "left", "right", "up", "down", "tab", "f", "p", "m", "space",
             "escape")


def _save_png(image: np.ndarray, path: Path) -> None:
    try:
        from PIL import Image
    except ImportError:
        import matplotlib.pyplot as plt

        plt.imsave(str(path), image)
    else:
        Image.fromarray(image).save(str(path))


class Window:
    """A glfw window with a moderngl context (``ctx``) the renderer draws with.

    width, height : the window's size in pixels (the renderer's viewport; not resizable)
    vsync : swap on the display's refresh; off by default, the client paces frames itself
    controller : what keys and mouse drags drive (``client.navigation.Navigator``), or None
    screenshot_dir : where P writes its PNGs
    fullscreen : cover the primary monitor at its current mode (``width`` and ``height`` become its size)
    public : a kiosk's window: no key closes it or toggles anything; all go to the controller
    marker : called when M or Space is pressed (``walkstream client --record-tour`` marks a stop)
    Raises ``WindowError`` when glfw cannot open a window (no display, no GL 3.3).
    """

    def __init__(self, width: int, height: int, title: str = "walkstream", vsync: bool = False, *,
                 controller: _Input | None = None, screenshot_dir: str | Path = ".", fullscreen: bool = False,
                 public: bool = False, marker: Callable[[], None] | None = None) -> None:
        global _windows
        glfw = self._glfw = _glfw()
        self.width, self.height, self.title = int(width), int(height), str(title)
        self.controller = controller
        self.screenshot_dir = Path(screenshot_dir)
        self.screenshots: list[Path] = []
        """PNGs written by P, in order."""
        self.renderer: Any = None
        """The renderer last presented (F toggles its ``false_colour``)."""
        self.public, self.marker = bool(public), marker
        self._pressed_at: tuple[float, float] | None = None  # where the left button went down, while it is
        self._handle = None
        self._initialised = False
        self._closed = False
        self._dragging = False
        self._cursor: tuple[float, float] | None = None  # last position the events reported
        self._want_shot = False
        self._keys = _key_names(glfw)
        glfw.set_error_callback(_on_glfw_error)
        _errors.clear()  # report this attempt's failure, not an old one
        with raster_threads():  # llvmpipe sizes its threads when it makes its screen: with GLX, at glfw's init
            initialised = glfw.init()
        if not initialised:
            raise WindowError(f"cannot initialise glfw ({_last_error('no reason given')}); {_DISPLAY_HINT}")
        self._initialised = True
        _windows += 1
        try:
            glfw.default_window_hints()
            for hint, value in ((glfw.CONTEXT_VERSION_MAJOR, 3), (glfw.CONTEXT_VERSION_MINOR, 3),
                                (glfw.OPENGL_PROFILE, glfw.OPENGL_CORE_PROFILE), (glfw.OPENGL_FORWARD_COMPAT, True),
                                (glfw.RESIZABLE, False), (glfw.DOUBLEBUFFER, True)):
                glfw.window_hint(hint, value)
            monitor = glfw.get_primary_monitor() if fullscreen else None
            if fullscreen:
                if not monitor:
                    raise WindowError(f"no monitor to go fullscreen on ({_last_error('no reason given')})")
                mode = glfw.get_video_mode(monitor)
                self.width, self.height = int(mode.size.width), int(mode.size.height)
            with raster_threads():
                self._handle = glfw.create_window(self.width, self.height, self.title, monitor, None)
            if not self._handle:
                raise WindowError(f"cannot open a {self.width}×{self.height} window with OpenGL 3.3 core "
                                  f"({_last_error('no reason given')}); {_DISPLAY_HINT}")
            glfw.make_context_current(self._handle)
            glfw.swap_interval(1 if vsync else 0)
            import moderngl

            try:
                self.ctx = moderngl.create_context(require=330)
            except Exception as exc:
                raise WindowError(f"the window's GL context is unusable: {exc}") from None
            glfw.set_key_callback(self._handle, self._on_key)
            glfw.set_mouse_button_callback(self._handle, self._on_button)
            glfw.set_cursor_pos_callback(self._handle, self._on_cursor)
            glfw.set_window_focus_callback(self._handle, self._on_focus)
        except BaseException:
            self.release()
            raise

    # ----------------------------------------------------------------- frame

    @property
    def should_close(self) -> bool:
        """The user closed the window (Escape or the window manager), or ``close`` was called."""
        return self._closed or self._handle is None or bool(self._glfw.window_should_close(self._handle))

    def close(self) -> None:
        """Ask the frame loop to stop (it checks ``should_close``)."""
        self._closed = True

    def poll(self) -> None:
        """Handle pending window events: key and mouse callbacks feed ``controller``."""
        if self._handle is not None:
            self._glfw.poll_events()

    def blit(self, renderer: Any) -> None:
        """Copy the renderer's last frame into the window's back buffer (no swap)."""
        self.ctx.copy_framebuffer(self.ctx.screen, renderer.fbo)

    def present(self, renderer: Any) -> None:
        """Show the renderer's last frame: blit it to the window and swap buffers."""
        self.renderer = renderer
        self.blit(renderer)
        if self._want_shot:
            self._want_shot = False
            self.screenshot()
        self._glfw.swap_buffers(self._handle)

    def read_screen(self) -> np.ndarray:
        """The window's back buffer as (height, width, 3) uint8, rows top-down.

        Read it after ``blit`` and before the next swap: GL leaves the back
        buffer's content undefined once it has been swapped.
        """
        w, h = self.ctx.screen.size
        data = self.ctx.screen.read(components=3, alignment=1)
        return np.frombuffer(data, np.uint8).reshape(h, w, 3)[::-1].copy()

    def screenshot(self, path: str | Path | None = None) -> Path:
        """Write what the window's back buffer holds as a PNG (default: a timestamped name in ``screenshot_dir``)."""
        if path is None:
            stamp = time.strftime("%Y%m%d-%H%M%S")
            path = self.screenshot_dir / f"walkstream-{stamp}-{len(self.screenshots)}.png"
        path = Path(path)
        _save_png(self.read_screen(), path)
        self.screenshots.append(path)
        return path

    # ----------------------------------------------------------------- input

    def on_key(self, name: str, pressed: bool) -> None:
        """A key went down or up, by name (``KEY_NAMES``); the glfw callback and tests both come here."""
        if self.public:
            if self.controller is not None:
                self.controller.key(name, pressed)
        elif pressed and name in ("m", "space") and self.marker is not None:
            self.marker()
        elif pressed and name == "escape":
            self.close()
        elif pressed and name == "f":
            self._toggle_false_colour()
        elif pressed and name == "p":
            self._want_shot = True  # taken in ``present``, while the back buffer holds the frame
        elif pressed and name == "tab":
            toggle = getattr(self.controller, "toggle", None)
            if toggle is not None and self._handle is not None:
                self._glfw.set_window_title(self._handle, f"{self.title} — {toggle()}")
        elif self.controller is not None:
            self.controller.key(name, pressed)

    def on_drag(self, dx: float, dy: float) -> None:
        """The mouse moved (dx, dy) pixels with the left button held."""
        if self.controller is not None:
            self.controller.look(dx, dy)

    def on_tap(self, x: float, y: float) -> None:
        """A click or tap at framebuffer pixel (x, y), y down: to the controller's ``tap``, if it has one."""
        tap = getattr(self.controller, "tap", None)
        if tap is not None:
            tap(x, y)

    def _pixels(self, x: float, y: float) -> tuple[float, float]:
        """Window coordinates (glfw's cursor) → framebuffer pixels (they differ on a high-density screen)."""
        w, h = self._glfw.get_window_size(self._handle)
        return x * self.width / max(w, 1), y * self.height / max(h, 1)

    def _toggle_false_colour(self) -> None:
        if self.renderer is not None:
            setattr(self.renderer, "false_colour", not bool(getattr(self.renderer, "false_colour", False)))

    def _on_key(self, handle: Any, key: int, scancode: int, action: int, mods: int) -> None:
        name = self._keys.get(key)
        if name is not None and action in (self._glfw.PRESS, self._glfw.RELEASE):
            self.on_key(name, action == self._glfw.PRESS)

    def _on_button(self, handle: Any, button: int, action: int, mods: int) -> None:
        if button == self._glfw.MOUSE_BUTTON_LEFT:
            self._dragging = action == self._glfw.PRESS
            x, y = self._glfw.get_cursor_pos(handle) if self._cursor is None else self._cursor
            if action == self._glfw.PRESS:
                self._pressed_at = (x, y)
            elif self._pressed_at is not None:
                x0, y0 = self._pressed_at
                self._pressed_at = None
                if abs(x - x0) <= TAP_SLOP and abs(y - y0) <= TAP_SLOP:
                    self.on_tap(*self._pixels(x, y))

    def _on_cursor(self, handle: Any, x: float, y: float) -> None:
        # Deltas between events, not from a query: a query answers where the pointer is now,
        # which is past motions still queued behind the button press.
        if self._dragging and self._cursor is not None:
            self.on_drag(x - self._cursor[0], y - self._cursor[1])
        self._cursor = (x, y)

    def _on_focus(self, handle: Any, focused: int) -> None:
        if not focused:
            self._dragging = False
            clear = getattr(self.controller, "clear_input", None)
            if clear is not None:
                clear()  # key releases go to the other window: nothing may stay held

    # ----------------------------------------------------------------- lifetime

    def release(self) -> None:
        """Close the window and its context; glfw ends with the last window. Safe to call twice."""
        global _windows
        glfw = self._glfw
        ctx = self.__dict__.pop("ctx", None)
        if ctx is not None:
            ctx.release()
        if self._handle is not None:
            glfw.destroy_window(self._handle)
            self._handle = None
        if self._initialised:
            self._initialised = False
            _windows -= 1
            if _windows == 0:
                glfw.terminate()

    def __enter__(self) -> "Window":
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()
