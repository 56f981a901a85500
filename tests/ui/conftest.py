"""Fixtures the browser-test modules share, each started once per module so that modules stay independent of
each other's state: ``shots`` (where screenshots go), ``data_dir`` (an empty data directory; a module overrides
it with the store its tests need), ``studio`` (the app with its embedded workers, on that directory) and
``page`` (headless Chromium on the studio, once it is ready). A failed browser test leaves a screenshot of each
page it had open (``page``, and those in a test's ``opened`` list) as it was, named after the test, and prints
where, with a line on each page's animation frames, the studio's messages it received, its long tasks and its
JavaScript errors (``browser_support.page_state``)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from browser_support import open_page, page_state, running_studio


@pytest.hookimpl(wrapper=True, tryfirst=True)
def pytest_runtest_makereport(item, call):
    report = yield
    if report.when == "call" and report.failed:
        pages = ([item.funcargs["page"]] if "page" in item.funcargs else []) + list(
            item.funcargs.get("opened") or []
        )
        folder = Path(item.funcargs.get("shots") or item.config.rootpath)
        for i, pg in enumerate(pages):
            path = folder / (f"FAILED-{item.name}" + (f"-{i}" if i else "") + ".png")
            try:
                if pg.is_closed():
                    continue
                pg.screenshot(path=str(path), timeout=10_000)
                report.sections.append(("screenshot of the failure", str(path)))
            except Exception as e:  # the page itself may be what failed
                report.sections.append(("screenshot of the failure", f"not taken: {e}"))
            try:
                report.sections.append(("the page at the failure", page_state(pg)))
            except Exception as e:
                report.sections.append(("the page at the failure", f"not read: {e}"))
    return report


@pytest.fixture(scope="module")
def shots(tmp_path_factory):
    d = tmp_path_factory.mktemp("screenshots")
    yield d
    print(f"\nscreenshots: {d}")


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("studio") / "data"


@pytest.fixture(scope="module")
def studio(data_dir):
    with running_studio(data_dir) as app:
        yield app


@pytest.fixture(scope="module")
def page(studio):
    with open_page(studio) as pg:
        yield pg
