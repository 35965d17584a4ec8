"""The kiosk's log: to stderr (the journal, under systemd) or to a file rotated under a size cap.

A kiosk runs for months; a log that grows without bound fills its disk. With a
``log_file`` the log rotates (``logging.handlers.RotatingFileHandler``) once a
file would pass ``log_max_mb``, keeping ``log_backups`` old files: at most
``log_max_mb × (log_backups + 1)`` on disk. One record longer than a whole
file (a runaway traceback) is cut to fit, or it alone would break the cap; and
the size check counts a record's bytes, not its characters (the standard
handler's), or wide characters — captions in Greek or Japanese — would.

``MB`` here is 10^6 bytes.
"""

from __future__ import annotations

import logging
import logging.handlers
import math
import os
import sys
from pathlib import Path

__all__ = ["setup_logging", "CappedFormatter", "CappedFileHandler", "FORMAT", "MB"]

MB = 1_000_000
FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
_MARK = "_walkstream_kiosk"  # set on the handler this module installs, so a second setup replaces it
_CUT = " …[cut]"


class CappedFormatter(logging.Formatter):
    """A formatter whose records never exceed ``limit`` bytes in UTF-8 (the line's end included)."""

    def __init__(self, fmt: str, limit: int) -> None:
        super().__init__(fmt)
        self.limit = limit

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        room = self.limit - 1  # the handler's newline
        data = text.encode("utf-8", "replace")
        if len(data) <= room:
            return text
        cut = _CUT.encode()
        return data[:max(0, room - len(cut))].decode("utf-8", "ignore") + _CUT


class CappedFileHandler(logging.handlers.RotatingFileHandler):
    """``RotatingFileHandler`` that measures a record in encoded bytes, so no file passes ``maxBytes``."""

    def shouldRollover(self, record: logging.LogRecord) -> bool:  # noqa: N802 (the base class's name)
        if os.path.exists(self.baseFilename) and not os.path.isfile(self.baseFilename):
            return False  # a log sent to /dev/null or a pipe is never rotated
        if self.stream is None:
            self.stream = self._open()
        data = f"{self.format(record)}\n".encode(self.encoding or "utf-8", "replace")
        self.stream.seek(0, 2)
        return self.stream.tell() + len(data) > self.maxBytes


def setup_logging(log_file: str | Path = "", log_max_mb: float = 10.0, log_backups: int = 3, *,
                  level: int = logging.INFO, logger: logging.Logger | None = None) -> logging.Handler:
    """Send ``logger`` (the root logger by default) to ``log_file``, rotated under the cap, or to stderr if "".

    Replaces a handler an earlier call installed; returns the new one (``handler.close()`` and
    ``logger.removeHandler`` undo it). ``ValueError`` naming the setting when one is out of range or
    the file cannot be opened.
    """
    if not (isinstance(log_max_mb, (int, float)) and math.isfinite(log_max_mb) and log_max_mb > 0):
        raise ValueError(f"log_max_mb: must be a positive number of megabytes, got {log_max_mb!r}")
    if not (isinstance(log_backups, int) and 1 <= log_backups <= 100):
        # With no backups RotatingFileHandler never rotates: the file would grow for ever.
        raise ValueError(f"log_backups: must be an integer in [1, 100], got {log_backups!r}")
    target = logging.getLogger() if logger is None else logger
    max_bytes = max(1024, int(log_max_mb * MB))
    handler: logging.Handler
    if str(log_file):
        path = Path(log_file)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            handler = CappedFileHandler(path, maxBytes=max_bytes, backupCount=log_backups, encoding="utf-8")
        except OSError as exc:
            raise ValueError(f"log_file: cannot write {str(path)!r}: {exc.strerror or exc}") from None
        handler.setFormatter(CappedFormatter(FORMAT, max_bytes))
    else:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter(FORMAT))
    setattr(handler, _MARK, True)
    for old in [h for h in target.handlers if getattr(h, _MARK, False)]:
        target.removeHandler(old)
        old.close()
    target.addHandler(handler)
    target.setLevel(level)
    return handler
