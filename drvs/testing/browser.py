"""Headless Chromium for the tests, driven by Selenium (Debian's chromium, chromium-driver and
python3-selenium; scripts/setup.sh installs them): :func:`unavailable` says why it cannot run here,
:func:`headless_chromium` gives a driver and leaves no browser or driver process behind, even when
the test fails.
"""

from __future__ import annotations

import contextlib
import shutil
from collections.abc import Iterator

import psutil

__all__ = ['CHROMEDRIVER', 'headless_chromium', 'unavailable']

CHROMEDRIVER = '/usr/bin/chromedriver'
QUIT_GRACE = 5.0
"""Seconds the browser and its driver are given to exit after ``quit`` before they are killed."""


def unavailable() -> str | None:
    """Why headless Chromium cannot run here (None: it can)."""
    try:
        import selenium  # noqa: F401
    except ImportError:
        return "python3-selenium is not installed (scripts/setup.sh installs Debian's)"
    if shutil.which('chromium') is None:
        return "chromium is not installed (scripts/setup.sh installs Debian's)"
    if shutil.which('chromedriver') is None and not shutil.which(CHROMEDRIVER):
        return "chromedriver is not installed (Debian's chromium-driver; scripts/setup.sh installs it)"
    return None


@contextlib.contextmanager
def headless_chromium(width: int = 1000, height: int = 800) -> Iterator:
    """A Selenium WebDriver on a new headless Chromium window of ``width`` x ``height`` pixels;
    on exit the browser quits, and whatever of it or its driver is left is killed."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    for argument in (
        '--headless=new',
        '--no-sandbox',  # as root, and in containers without user namespaces
        '--disable-dev-shm-usage',
        '--disable-gpu',
        '--no-first-run',
        '--disable-extensions',
        '--disable-background-networking',
        f'--window-size={width},{height}',
    ):
        options.add_argument(argument)
    options.binary_location = shutil.which('chromium') or '/usr/bin/chromium'
    service = Service(shutil.which('chromedriver') or CHROMEDRIVER)
    driver = None
    try:
        driver = webdriver.Chrome(service=service, options=options)
        yield driver
    finally:
        family = []
        process = getattr(service, 'process', None)
        if process is not None:
            with contextlib.suppress(psutil.Error):
                family = [psutil.Process(process.pid), *psutil.Process(process.pid).children(recursive=True)]
        if driver is not None:
            with contextlib.suppress(Exception):
                driver.quit()
        with contextlib.suppress(Exception):
            service.stop()
        _, alive = psutil.wait_procs(family, timeout=QUIT_GRACE)
        for leftover in alive:
            with contextlib.suppress(psutil.Error):
                leftover.kill()
        psutil.wait_procs(alive, timeout=QUIT_GRACE)
