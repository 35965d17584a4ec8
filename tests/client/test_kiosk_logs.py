"""The kiosk's log rotates under its size cap: whatever is written, the files never hold more than the cap."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from client.kiosk.logs import MB, setup_logging


def _files(folder: Path) -> list[Path]:
    return sorted(folder.glob("kiosk.log*"))


@pytest.fixture
def logger():
    log = logging.getLogger("walkstream.test.kiosk-logs")
    log.propagate = False
    yield log
    for h in list(log.handlers):
        log.removeHandler(h)
        h.close()


def test_writing_past_the_cap_rotates_and_keeps_the_total_under_it(tmp_path: Path, logger) -> None:
    max_mb, backups = 0.01, 3  # 10 kB files
    setup_logging(tmp_path / "logs" / "kiosk.log", max_mb, backups, logger=logger)
    for i in range(2000):  # ~150 kB: many times the cap
        logger.info("frame %d drawn from the cache while the server is away", i)
    files = _files(tmp_path / "logs")
    assert [f.name for f in files] == ["kiosk.log", "kiosk.log.1", "kiosk.log.2", "kiosk.log.3"]
    sizes = [f.stat().st_size for f in files]
    assert all(s <= max_mb * MB for s in sizes) and sum(sizes) <= max_mb * MB * (backups + 1)
    assert "frame 1999 " in files[0].read_text()  # the newest lines are in the live file


wide = st.text(st.characters(min_codepoint=0x80, exclude_categories=("Cs",)), max_size=600)  # 2–4 bytes each


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.one_of(st.text(max_size=6000), wide), min_size=1, max_size=60), st.integers(1, 4))
def test_no_record_breaks_the_cap_however_long_or_wide(tmp_path_factory, messages: list[str], backups: int) -> None:
    folder = tmp_path_factory.mktemp("logs")
    log = logging.getLogger(f"walkstream.test.kiosk-logs.{folder.name}")
    log.propagate = False
    handler = setup_logging(folder / "kiosk.log", 0.002, backups, logger=log)  # 2 kB files: records exceed them
    try:
        for m in messages:
            log.warning("%s", m)
    finally:
        log.removeHandler(handler)
        handler.close()
    sizes = [f.stat().st_size for f in _files(folder)]
    assert len(sizes) <= backups + 1
    assert all(s <= 2000 for s in sizes) and sum(sizes) <= 2000 * (backups + 1)


def test_wide_characters_count_as_the_bytes_they_take(tmp_path: Path, logger) -> None:
    """Records of 3-byte characters: counted in characters they would pass the cap (the standard handler does)."""
    setup_logging(tmp_path / "kiosk.log", 0.002, 2, logger=logger)
    for _ in range(40):
        logger.warning("%s", "€" * 100)  # ~350 bytes in ~150 characters
    sizes = [f.stat().st_size for f in _files(tmp_path)]
    assert len(sizes) == 3 and max(sizes) <= 2000


def test_no_file_means_stderr(capsys, logger) -> None:
    handler = setup_logging("", logger=logger)
    assert isinstance(handler, logging.StreamHandler) and not isinstance(handler, logging.FileHandler)
    logger.warning("reconnecting to ws://b/ws")
    assert "WARNING walkstream.test.kiosk-logs: reconnecting to ws://b/ws" in capsys.readouterr().err


def test_a_second_setup_replaces_the_first(tmp_path: Path, logger) -> None:
    setup_logging(tmp_path / "a.log", logger=logger)
    setup_logging(tmp_path / "b.log", logger=logger)
    files = [h for h in logger.handlers if isinstance(h, logging.FileHandler)]  # (pytest adds capture handlers)
    assert len(files) == 1 and files[0].baseFilename.endswith("b.log")


@pytest.mark.parametrize("kw, field", [({"log_max_mb": 0}, "log_max_mb"), ({"log_max_mb": float("inf")}, "log_max_mb"),
                                       ({"log_backups": 0}, "log_backups"), ({"log_backups": 1.5}, "log_backups")])
def test_bad_settings_are_refused_naming_the_field(tmp_path: Path, logger, kw: dict, field: str) -> None:
    with pytest.raises(ValueError, match=f"^{field}: "):
        setup_logging(tmp_path / "kiosk.log", **{"log_max_mb": 1.0, "log_backups": 2, **kw}, logger=logger)


def test_an_unwritable_file_is_refused_naming_the_field(tmp_path: Path, logger) -> None:
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("")
    with pytest.raises(ValueError, match="^log_file: cannot write"):
        setup_logging(blocker / "kiosk.log", logger=logger)
