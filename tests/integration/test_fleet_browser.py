"""The fleet page in a real browser: Debian's chromium, headless, driven by selenium against a real server.

The page is opened as an administrator would, by typing ``/fleet?token=...``; the test reads what the page
shows (the kiosk's id and tour, its frame-time sparkline) and waits, without touching the browser, for the
page's own reloads to show the STALE mark once the kiosk's heartbeats stop.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import httpx
import pytest

from bench.demo import ServerProcess

from .kiosk_stub import KioskStub

CHROMIUM, CHROMEDRIVER = Path("/usr/bin/chromium"), Path("/usr/bin/chromedriver")


@pytest.fixture()
def browser():
    """A headless chromium (a fresh profile) under chromedriver; fails, never skips, when either is missing."""
    missing = [str(p) for p in (CHROMIUM, CHROMEDRIVER) if not p.exists()]
    if missing:
        pytest.fail(f"the fleet page's browser test needs Debian's chromium: {', '.join(missing)} not found "
                    "(apt-get install chromium chromium-driver, or run scripts/bootstrap.sh)")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    profile = tempfile.mkdtemp(prefix="walkstream-chromium-")
    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 f"--user-data-dir={profile}", "--window-size=1600,900"):
        options.add_argument(flag)
    driver = webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=options)
    try:
        yield driver
    finally:
        driver.quit()
        shutil.rmtree(profile, ignore_errors=True)


def test_the_fleet_page_shows_a_kiosk_and_marks_it_stale_when_its_heartbeats_stop(demo_store, browser):
    from selenium.common.exceptions import NoSuchElementException, StaleElementReferenceException
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    def kiosk_row():
        return browser.find_element(By.CSS_SELECTOR, 'tr.kiosk[data-kiosk="gallery-2"]')

    # Each reload replaces the page under the test's feet: an element read mid-reload is read again.
    wait = WebDriverWait(browser, 30, poll_frequency=0.2,
                         ignored_exceptions=(NoSuchElementException, StaleElementReferenceException))
    with ServerProcess([demo_store], replica="museum") as srv:
        # Refused without the token, in the browser as over plain HTTP.
        assert httpx.get(srv.http + "/fleet", timeout=10).status_code == 401
        browser.get(srv.http + "/fleet")
        assert "admin token is required" in browser.find_element(By.TAG_NAME, "body").text

        with KioskStub(srv.url, "gallery-2", interval=0.5, tour="old-town", stop=4) as kiosk:
            browser.get(f"{srv.http}/fleet?token={srv.admin_token}")
            assert browser.current_url == srv.http + "/fleet"  # the token left the address bar for a cookie
            row = wait.until(lambda d: kiosk_row())
            assert browser.title == "walkstream fleet · museum"
            cells = {c.get_attribute("class").split()[-1]: c.text for c in row.find_elements(By.TAG_NAME, "td")}
            assert cells["id"] == "gallery-2" and cells["tour"] == "old-town · stop 4"
            assert cells["state"] == "attract" and "STALE" not in row.text and cells["fps"] == "60.0"
            line = row.find_element(By.CSS_SELECTOR, "td.frames svg polyline")
            points = [tuple(map(float, p.split(","))) for p in line.get_attribute("points").split()]
            assert len(points) >= 12 and len({y for _, y in points}) > 1  # frame times, drawn as a line
            assert line.rect["width"] > 100  # laid out by the browser, not just present in the source
            sessions = browser.find_element(By.ID, "sessions").text
            assert kiosk.session in sessions and "gallery-2" in sessions

            kiosk.beating.clear()  # the kiosk stops reporting; the page reloads on its own
            mark = wait.until(lambda d: kiosk_row().find_element(By.CSS_SELECTOR, ".mark.stale"))
            assert mark.text == "STALE" and mark.is_displayed()
            assert "stale" in kiosk_row().get_attribute("class").split()
