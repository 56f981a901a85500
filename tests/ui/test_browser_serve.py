"""`studio serve` in a real browser, as a user starts it: a subprocess that prints its URL, the page in Debian's
headless Chromium (Playwright), teleop waiting for a sim worker, a clean SIGTERM.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from studio.backend import bus

sys.path.insert(0, str(Path(__file__).resolve().parent))
import browser_support as ui
from browser_support import THROTTLE_RAF

pytestmark = [pytest.mark.browser, pytest.mark.timeout(420)]


def test_serve_prints_its_url_and_waits_for_external_workers(tmp_path):
    """`studio serve` as a user runs it (here with `--workers none`; the embedded default is what the other
    tests' in-process app starts): URL printed, page up, teleop waiting for a sim worker, clean SIGTERM."""
    from playwright.sync_api import sync_playwright

    env = dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))
    bus_port = bus.free_loopback_port()
    cmd = [
        sys.executable,
        "-m",
        "studio.cli",
        "serve",
        "--port",
        str(bus.free_loopback_port()),
        "--workers",
        "none",
        "--data-dir",
        str(tmp_path / "data"),
        "--listen",
        bus.loopback_endpoint(bus_port),
    ]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
    try:
        url, line = None, ""
        deadline = time.time() + 60
        while time.time() < deadline and url is None:
            line = proc.stdout.readline()
            if "OSVI Studio running at" in line:
                url = line.split("running at")[1].split()[0]
            elif proc.poll() is not None:
                break
        assert url and url.startswith("http://127.0.0.1:"), f"no URL printed (last line: {line!r})"
        assert "no workers" in line and f"127.0.0.1:{bus_port}" in line
        with sync_playwright() as p:
            browser = ui.launch(p)
            page = browser.new_page(viewport={"width": 1100, "height": 720})
            page.add_init_script(THROTTLE_RAF)
            page.goto(url)
            page.get_by_text("Waiting for a sim worker").filter(visible=True).first.wait_for(timeout=60_000)
            assert page.locator("canvas").first.is_visible()
            ui.open_tab(page, "Workers", "No worker is connected")
            browser.close()
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
    assert proc.returncode == 0, "studio serve did not stop cleanly on SIGTERM"
