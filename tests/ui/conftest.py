"""Fixtures of the UI tests: headless Chromium (Debian's) driven by Playwright, and which nodes feed the relay."""

from __future__ import annotations

import os

import pytest

from tests.ui.helpers import REAL_PIPELINES, launch_chromium

FEEDER_ENV = "DCUSCOPE_UI_FEEDER"


@pytest.fixture(scope="module")
def browser():
    # Module scope: Playwright's sync API keeps an asyncio loop running in the main thread
    # while it is open, which would break asyncio.run() in any test that ran after it.
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        browser = launch_chromium(playwright)
        try:
            yield browser
        finally:
            browser.close()


@pytest.fixture(scope="session")
def feeder_kind() -> str:
    """"pipeline": real ``dcuscope run --probes --relay`` processes (the default once they exist);
    "sim": ``probes.ship.simnode`` processes. ``DCUSCOPE_UI_FEEDER=sim|pipeline`` chooses."""
    kind = os.environ.get(FEEDER_ENV) or ("pipeline" if REAL_PIPELINES else "sim")
    if kind not in ("sim", "pipeline"):
        raise ValueError(f"{FEEDER_ENV} must be sim or pipeline, not {kind!r}")
    return kind
