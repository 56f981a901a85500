"""What the browser tests share: launching Debian's Chromium, waiting on the app, clicking, screenshots.

Each browser test module starts its own app (``running_studio``) and page (``open_page``) as module-scoped
fixtures, so that modules stay independent of each other's state.
"""

from __future__ import annotations

import contextlib
import time
import warnings
from collections.abc import Iterator
from pathlib import Path

import pytest

from studio.backend import bus
from studio.bench.click_demo import screen_point  # noqa: F401 (the tests' name for it)
from studio.bench.ui import CHROMIUM, CHROMIUM_ARGS, WEBGL_ARGS

THROTTLE_RAF = """(() => { const raf = window.requestAnimationFrame.bind(window);
  window.requestAnimationFrame = (cb) => setTimeout(() => raf(cb), 200); })();"""


@contextlib.contextmanager
def running_studio(data_dir: Path) -> Iterator:
    """A :class:`StudioApp` with its embedded sim worker and trainer on a private bus, stopped afterwards."""
    from studio.ui.app import StudioApp

    app = StudioApp(
        port=bus.free_loopback_port(),
        data_dir=data_dir,
        bus_config=bus.BusConfig.hub([bus.loopback_endpoint(bus.free_loopback_port())]),
    )
    try:
        assert app.wait_for_workers(90), "the embedded workers did not join"
        yield app
    finally:
        app.stop()


@contextlib.contextmanager
def open_page(studio, ready: str = "ready. Drag the gizmo", viewport=(1100, 720)) -> Iterator:
    """A headless Chromium page on the studio, once it shows ``ready``."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = launch(p)
        pg = browser.new_page(viewport={"width": viewport[0], "height": viewport[1]})
        pg.add_init_script(THROTTLE_RAF)
        pg.goto(studio.url)
        pg.get_by_text(ready).first.wait_for(timeout=90_000)
        yield pg
        browser.close()


def launch(p):
    if not Path(CHROMIUM).exists():
        pytest.fail(f"{CHROMIUM} is missing: ./run test installs Debian's chromium")
    return p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS + WEBGL_ARGS["llvmpipe"])


def colours(path: Path, box=(0, 0, 700, 700)) -> int:
    from PIL import Image

    return len(Image.open(path).convert("RGB").crop(box).getcolors(maxcolors=1 << 20) or [])


def shot(page, path: Path, scroll_to: str | None = None) -> None:
    """A screenshot for people to look at; a machine too loaded to render one in time only warns."""
    from playwright.sync_api import Error as PlaywrightError

    if scroll_to is not None:
        try:
            page.get_by_text(scroll_to).first.scroll_into_view_if_needed(timeout=45_000)
        except PlaywrightError:  # timed out, or the text was re-rendered while scrolling: no picture lost
            warnings.warn(f"could not scroll to {scroll_to!r} for {path.name}", stacklevel=2)
    for attempt in range(2):
        try:
            page.screenshot(path=str(path), timeout=45_000)
            return
        except PlaywrightError:
            if attempt:
                warnings.warn(f"no screenshot {path.name}: the page did not render in time", stacklevel=2)


def drawn(page, frames: int = 2) -> None:
    """Wait until the page has drawn ``frames`` animation frames: what was sent to it is on the screen."""
    page.evaluate(
        """(n) => new Promise((done) => {
             const step = (k) => (k <= 0 ? done() : requestAnimationFrame(() => step(k - 1)));
             step(n);
           })""",
        frames,
    )


def sim_ticks(client, ticks: int, timeout: float = 30) -> None:
    """Wait until the teleop session's simulation has advanced ``ticks`` control ticks (its pose stream)."""
    start = client.latest_pose().step
    if client.poses.wait_until(lambda f: f.step >= start + ticks, timeout) is None:
        raise AssertionError(f"the simulation did not advance {ticks} ticks in {timeout} s")


def next_pose(client, version: int, timeout: float = 10) -> int:
    """Wait for the session's next pose frame after ``version``; returns the new version."""
    _, newer = client.poses.wait_newer(version, timeout)
    if newer <= version:
        raise AssertionError(f"no pose frame from the simulation in {timeout} s")
    return newer


def click(locator) -> None:
    """Click without Playwright's stability wait: that waits on animation frames, which software WebGL on a
    loaded machine delivers slowly; the elements clicked here are plain buttons and tabs."""
    locator.click(force=True, timeout=60_000)


def click_until(page, locator, shows: str, attempts: int = 3) -> None:
    """Click until the page shows ``shows``: a click that lands while a loaded machine is still building the page
    can be lost (seen in full-suite runs, on tabs and on the Inspect tab's Open), and waiting longer on a click
    that never arrived does not help. Fails if the text never appears."""
    click_until_done(locator, lambda: page.get_by_text(shows).first.wait_for(timeout=30_000), attempts)


def click_until_done(locator, wait_done, attempts: int = 3) -> None:
    """Click, then ``wait_done()`` (raises on timeout); click again while it times out, at most ``attempts`` times."""
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    for attempt in range(attempts):
        click(locator)
        try:
            wait_done()
            return
        except (PlaywrightTimeout, AssertionError):
            if attempt == attempts - 1:
                raise


def choose(page, combobox: str, option, taken, what: str, state=None, timeout: float = 20, attempts: int = 3):
    """Pick ``option`` (a name or pattern) in the dropdown ``combobox`` and wait until ``taken()``: open the list
    (until the option shows), click it, and reopen and click again while the app has not taken it. A click on an
    option of a list that is still opening can close the list without choosing (seen on a loaded machine: the app
    never heard of the choice); an app that refuses the choice fails the last attempt with ``state()``."""
    exact = isinstance(option, str)
    locator = (
        page.get_by_role("option", name=option, exact=True)
        if exact
        else page.get_by_role("option", name=option)
    )
    for attempt in range(attempts):
        click_until_done(
            page.get_by_role("combobox", name=combobox), lambda: locator.wait_for(timeout=10_000)
        )
        click(locator)
        try:
            return wait(taken, timeout, what, state)
        except AssertionError:
            if attempt == attempts - 1:
                raise


def open_tab(page, name: str, shows: str, attempts: int = 3) -> None:
    """Open a tab, re-clicking while its content does not show (``click_until``)."""
    click_until(page, page.get_by_role("tab", name=name), shows, attempts)


def tab(studio):
    (tab,) = studio.tabs.values()
    return tab


def wait(predicate, timeout: float, what: str, state=None):
    """Poll ``predicate`` until it is truthy; on timeout, fail with ``state()`` (what the app showed) if given."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(
        f"timed out after {timeout} s waiting for {what}" + (f"; {state()}" if state else "")
    )


def teleop_state(tab) -> str:
    """What the teleop panel shows and what its tab is busy with, for failure messages."""
    return (
        f"status {tab.teleop.status.content!r}, tab actions {tab.actions}, recording {tab.teleop._recording}"
    )


def stop_and_save(page, tab) -> None:
    """Click Stop & save until the panel took it (no longer recording, or saving), then wait for the store.
    Re-clicking is safe: a Stop & save after the first one is a no-op."""
    tp = tab.teleop
    click_until_done(
        page.get_by_role("button", name="Stop & save"),
        lambda: wait(
            lambda: not tp.status.content.startswith("Recording"),
            30,
            "Stop & save to be taken",
            lambda: teleop_state(tab),
        ),
    )
    wait(
        lambda: tp.status.content.startswith("Saved"),
        120,
        "the episode to be stored",
        lambda: teleop_state(tab),
    )
