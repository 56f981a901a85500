"""The studio in a real browser: headless Chromium (Debian's) driven by Playwright against `studio serve`."""

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

CHROMIUM = "/usr/bin/chromium"
pytestmark = pytest.mark.browser


@pytest.fixture()
def studio_url(tmp_path):
    env = dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))
    proc = subprocess.Popen(
        [sys.executable, "-m", "studio.cli", "serve", "--port", "8431", "--data-dir", str(tmp_path / "data")],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
    )
    url = None
    deadline = time.time() + 60
    while time.time() < deadline and url is None:
        line = proc.stdout.readline()
        if "OSVI Studio running at" in line:
            url = line.split("running at")[1].split()[0]
        elif proc.poll() is not None:
            break
    assert url, "studio serve did not print its URL"
    yield url
    proc.terminate()
    proc.wait(timeout=10)


def test_page_loads_and_renders_the_scene(studio_url, tmp_path):
    from playwright.sync_api import sync_playwright

    if not Path(CHROMIUM).exists():
        pytest.fail(f"{CHROMIUM} is missing: ./run test installs Debian's chromium")
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=[
            "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
            "--disable-sync", "--no-first-run"])
        page = browser.new_page(viewport={"width": 1280, "height": 800})
        page.goto(studio_url)
        page.get_by_text("Teleop & record").first.wait_for(timeout=30000)
        page.get_by_text("Ready.").first.wait_for(timeout=30000)
        time.sleep(2)
        shot = tmp_path / "teleop.png"
        page.screenshot(path=str(shot))
        canvas = page.locator("canvas").first
        assert canvas.is_visible()
        # The 3D view is not blank: the canvas has many distinct colours.
        from PIL import Image

        img = Image.open(shot).convert("RGB").crop((0, 0, 900, 800))
        assert len(img.getcolors(maxcolors=1 << 20) or []) > 200
        browser.close()
