"""What the browser tests share: launching Debian's Chromium, waiting on the app, clicking, screenshots.

Each browser test module starts its own app (``running_studio``) and page (``open_page``) through the module-scoped
fixtures of ``conftest.py``, so that modules stay independent of each other's state.
"""

from __future__ import annotations

import contextlib
import warnings
import weakref
from collections.abc import Iterator
from pathlib import Path

import pytest

from studio.backend import bus
from studio.bench.click_demo import (  # noqa: F401 (the tests' names for them)
    PAUSE_DRAWING,
    RESUME_DRAWING,
    THROTTLE_RAF,
    click_button,
    press,
    screen_point,
)
from studio.bench.ui import CHROMIUM, CHROMIUM_ARGS, WEBGL_ARGS

#: The apps ``running_studio`` has started in this process and not stopped: what :func:`wait` waits on.
_RUNNING: list = []


@contextlib.contextmanager
def running_studio(data_dir: Path) -> Iterator:
    """A :class:`StudioApp` with its embedded sim worker and trainer on a private bus, stopped afterwards."""
    from studio.ui.app import StudioApp

    app = StudioApp(
        port=bus.free_loopback_port(),
        data_dir=data_dir,
        bus_config=bus.BusConfig.hub([bus.loopback_endpoint(bus.free_loopback_port())]),
    )
    _RUNNING.append(app)
    try:
        assert app.wait_for_workers(90), "the embedded workers did not join"
        yield app
    finally:
        _RUNNING.remove(app)
        app.stop()


@contextlib.contextmanager
def open_page(studio, ready: str = "ready. Drag the gizmo", viewport=(1100, 720)) -> Iterator:
    """A headless Chromium page on the studio, once it shows ``ready``."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = launch(p)
        pg = browser.new_page(viewport={"width": viewport[0], "height": viewport[1]})
        watch_page(pg)
        pg.add_init_script(THROTTLE_RAF)
        pg.goto(studio.url)
        pg.get_by_text(ready).filter(visible=True).first.wait_for(timeout=90_000)
        yield pg
        browser.close()


#: The JavaScript errors a page reported (uncaught exceptions and console errors), by page: what a failed test's
#: report lists, as a script that threw can leave a page that no longer applies what the studio sends. Held only
#: as long as the page object is.
_ERRORS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()

#: How the page's animation loop (through THROTTLE_RAF, which the page's drawing and message handling wait on) is
#: doing: frames given in about three seconds, and whether the browser calls the page hidden or a test paused it.
_FRAME_PROBE = """async () => {
  const t0 = performance.now(); let frames = 0;
  await new Promise((done) => {
    const tick = () => { frames++; if (performance.now() - t0 < 3000) requestAnimationFrame(tick); else done(); };
    requestAnimationFrame(tick);
    setTimeout(done, 6000);
  });
  return {frames, ms: Math.round(performance.now() - t0), visibility: document.visibilityState,
          paused: !!window.__studioBackground};
}"""


#: Counts, in the page, the message batches viser's websocket worker hands the page and the main thread's long
#: tasks (over 50 ms), for :func:`page_state`: whether what the studio sends is arriving, and how busy the page is.
_TRAFFIC_PROBE = """(() => {
  const t = (window.__studioTraffic = {batches: 0, messages: 0, last: null, long: []});
  const Base = window.Worker;
  window.Worker = class extends Base {
    constructor(...args) {
      super(...args);
      this.addEventListener("message", (e) => {
        if (e.data && e.data.type === "message_batch") {
          t.batches++; t.messages += e.data.messages.length; t.last = performance.now();
        }
      });
    }
  };
  try {
    new PerformanceObserver((list) => {
      for (const e of list.getEntries()) t.long.push([e.startTime, e.duration]);
      if (t.long.length > 2000) t.long.splice(0, 1000);
    }).observe({type: "longtask"});
  } catch (e) {}
})();"""

_TRAFFIC_STATE = """() => {
  const t = window.__studioTraffic, now = performance.now();
  if (!t) return null;
  const recent = t.long.filter(([start]) => start > now - 30000);
  return {batches: t.batches, messages: t.messages, ago: t.last === null ? null : (now - t.last) / 1000,
          long: recent.length, longS: recent.reduce((a, [, d]) => a + d, 0) / 1000,
          longest: recent.reduce((a, [, d]) => Math.max(a, d), 0) / 1000};
}"""


def watch_page(pg) -> None:
    """Keep the JavaScript errors ``pg`` reports and count the studio's messages it receives, for
    :func:`page_state` (call before the page loads the studio)."""
    pg.add_init_script(_TRAFFIC_PROBE)
    _ERRORS[pg] = errors = []
    pg.on("pageerror", lambda e: errors.append(f"uncaught: {e}"))
    pg.on("console", lambda m: errors.append(f"console: {m.text}") if m.type == "error" else None)


def page_state(pg) -> str:
    """One line on what a page is doing, for a failure report: its animation frames over about three seconds, its
    visibility, and (for a page :func:`watch_page` watched) the studio's messages it received, its long tasks
    and the last JavaScript errors it reported."""
    s = pg.evaluate(_FRAME_PROBE)
    line = f"{s['frames']} animation frames in {s['ms']} ms, {s['visibility']}"
    line += ", drawing paused by the test" if s["paused"] else ""
    t = pg.evaluate(_TRAFFIC_STATE)
    if t is not None:
        ago = "never" if t["ago"] is None else f"the last {t['ago']:.1f} s ago"
        line += (
            f"; {t['batches']} message batches ({t['messages']} messages) received, {ago}; in the last 30 s"
            f" {t['long']} long tasks, {t['longS']:.1f} s in all, the longest {t['longest']:.1f} s"
        )
    errors = _ERRORS.get(pg)
    if errors is not None:
        last = " | ".join(e[:300] for e in errors[-3:])
        line += f"; {len(errors)} JavaScript errors" + (f", the last: {last}" if errors else "")
    return line


@contextlib.contextmanager
def in_background(pages) -> Iterator:
    """Pause the drawing of ``pages`` (THROTTLE_RAF pages) inside the block, as a browser pauses its background
    tabs: headless Chromium draws every open page in software, and a page loading beside one that draws waits
    for the CPU (a second tab took 11–50 s to connect and 23–59 s to be ready beside six busy processes, and
    over 120 s in an overloaded test run)."""
    paused = [pg for pg in pages if not pg.is_closed()]
    for pg in paused:
        pg.evaluate(PAUSE_DRAWING)
    try:
        yield
    finally:
        for pg in paused:
            if not pg.is_closed():
                pg.evaluate(RESUME_DRAWING)


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
    """Click as a person does: Playwright waits until the element is visible, still (not moving between two
    drawn frames), enabled and the topmost element at its centre, then clicks it once. Forcing the click past
    those checks is what lost clicks before: a forced click at a list option still sliding open, or at a tab the
    panel had just moved, landed on whatever was there.

    Headless Chromium drawing WebGL on the CPU has stopped drawing frames for over a minute while the machine's
    two cores were busy (a training job beside it): Playwright's stillness check waits for drawn frames and never
    passed, and a screenshot timed out. After 20 s the click is therefore made as :func:`press` makes it (the
    same checks, read without frames), with a warning saying what the page and the browser were doing."""
    click_button(locator.page, locator)  # warns when it had to press


def double_click(page, locator) -> None:
    """Double-click as a person does: two presses milliseconds apart at the centre of ``locator``, once it is
    visible, enabled, on top and still (:func:`studio.bench.click_demo.press`). Not Playwright's ``dblclick``: when
    the first click disables the button before the second press, the browser swallows that press, Playwright takes
    it for a missed click and repeats the whole double click once the button is enabled again, clicking a second
    time what no person clicked twice. Nor a hover then presses at the box read after it: on a loaded machine the
    panel moved in between and the presses reached the button below (Fine-tune instead of Start)."""
    press(page, locator, count=2)


def click_and_see(page, locator, shows: str) -> None:
    """Click once, then wait until the page shows ``shows``."""
    click(locator)
    page.get_by_text(shows).filter(visible=True).first.wait_for(timeout=60_000)


def click_until(locator, done, what: str, state=None, tries: int = 3, each: float = 20) -> None:
    """Click an idempotent action until ``done()`` holds: a person clicks again when nothing happened. On a loaded
    machine a click can land while the panel is still moving (a folder opening above it) and reach nothing;
    clicking twice what already worked only repeats it. Fails after ``tries`` clicks."""
    for attempt in range(1, tries + 1):
        click(locator)
        try:
            wait(done, each, what, state)
            return
        except AssertionError:
            if attempt == tries:
                raise
            warnings.warn(
                f"clicked again: {what} had not happened {each:g} s after click {attempt}", stacklevel=2
            )


def click_and_wait(locator, wait_done) -> None:
    """Click once, then ``wait_done()`` (which raises if what the click does never happens)."""
    click(locator)
    wait_done()


def choose(page, combobox: str, option, taken, what: str, state=None, timeout: float = 20):
    """Pick ``option`` (a name or pattern) in the dropdown ``combobox`` and wait until the app took it
    (``taken()``); fails with ``state()``, what the app shows, if it does not."""
    exact = isinstance(option, str)
    locator = (
        page.get_by_role("option", name=option, exact=True)
        if exact
        else page.get_by_role("option", name=option)
    )
    click(page.get_by_role("combobox", name=combobox))
    click(locator)
    return wait(taken, timeout, what, state)


def open_tab(page, name: str, shows: str, tries: int = 3) -> None:
    """Open a tab and wait until its content shows; clicked again if it did not open (a tab already open stays
    open when clicked), as a person would."""
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    for attempt in range(1, tries + 1):
        click(page.get_by_role("tab", name=name))
        try:
            page.get_by_text(shows).filter(visible=True).first.wait_for(
                timeout=20_000 if attempt < tries else 60_000
            )
            return
        except PlaywrightTimeout:
            if attempt == tries:
                raise
            warnings.warn(
                f"clicked again: tab {name!r} did not show {shows!r} after click {attempt}", stacklevel=2
            )


def tab(studio):
    (tab,) = studio.tabs.values()
    return tab


def wait(predicate, timeout: float, what: str, state=None):
    """Wait until ``predicate`` is truthy, checking it each time the running app changes what it shows
    (``StudioApp.wait_until``); on timeout, fail with ``state()`` (what the app showed) if given."""
    if not _RUNNING:
        raise AssertionError("ui.wait waits on a running studio: start one with running_studio")
    value = _RUNNING[-1].wait_until(predicate, timeout)
    if value:
        return value
    raise AssertionError(
        f"timed out after {timeout} s waiting for {what}" + (f"; {state()}" if state else "")
    )


def teleop_state(tab) -> str:
    """What the teleop panel shows and what its tab is busy with, for failure messages."""
    return (
        f"status {tab.teleop.status.content!r}, tab actions {tab.actions}, recording {tab.teleop._recording}"
    )


def stop_and_save(page, tab) -> None:
    """Click Stop & save, wait until the panel took it (no longer recording, or saving), then for the store."""
    tp = tab.teleop
    click_and_wait(
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
