"""`studio bench click-demo`: how long a person takes from opening the page to a saved successful demonstration.

Starts the studio in this process (hub, embedded workers, viser server) on free loopback ports, opens it in
headless Chromium (Playwright, Debian's ``/usr/bin/chromium``) and records demonstrations the way a person does
with click-to-reach: real mouse clicks on the 3D canvas where the object and the zone appear, and clicks on the
panel's Record, Down, Close, Up, Open and Stop & save buttons, each after the arm has arrived (as a person
watches it). :class:`ClickPerson` is that person; the browser tests use it too.

Reported: ``seconds_to_first_saved`` (from ``page.goto`` to the first successful demonstration stored),
``page_ready_s`` (page open to the teleop session ready), and per demonstration its actions, simulated seconds,
wall seconds and success. ``--task``/``--seeds`` record more (the task and seed are set on the panel's widgets
between demonstrations, as a person's pick would); ``--data-dir`` keeps them, e.g. to imitate them with
``studio eval``.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from studio.bench.ui import CHROMIUM, CHROMIUM_ARGS, WEBGL_ARGS

#: Slows the page's animation frames to ~5 fps so software WebGL does not starve the simulation on 2 cores. While
#: ``window.__studioBackground`` is true the page draws nothing, as a browser pauses a background tab's frames
#: (headless Chromium draws every page it has open; see :data:`PAUSE_DRAWING`).
THROTTLE_RAF = """(() => { const raf = window.requestAnimationFrame.bind(window);
  const later = (cb) => setTimeout(() => (window.__studioBackground ? later(cb) : raf(cb)), 200);
  window.requestAnimationFrame = later; })();"""

#: Scripts that pause and resume a THROTTLE_RAF page's drawing.
PAUSE_DRAWING, RESUME_DRAWING = "window.__studioBackground = true", "window.__studioBackground = false"


def wait_until(
    predicate: Callable[[], Any], timeout: float, what: str, state: Callable[[], str] | None = None
):
    """Poll ``predicate`` until truthy; on timeout raise AssertionError naming ``what`` (and ``state()``)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(
        f"timed out after {timeout} s waiting for {what}" + (f"; {state()}" if state else "")
    )


#: Where a button's centre is, whether it is visible and enabled, and whether it is on top there (what a press at
#: that point reaches): read with one evaluation, which needs no drawn frame.
_BUTTON_AT = """(el) => {
  const at = () => {
    const b = el.getBoundingClientRect(), x = b.left + b.width / 2, y = b.top + b.height / 2;
    const top = document.elementFromPoint(x, y);
    return {b, x, y, onTop: !!top && el.contains(top)};
  };
  let p = at();
  if (!p.onTop) {  // scrolled out of its panel or the window: bring it to the middle, at once (no frame needed)
    el.scrollIntoView({block: 'center', inline: 'nearest', behavior: 'instant'});
    p = at();
  }
  const shown = p.b.width > 0 && p.b.height > 0 && getComputedStyle(el).visibility !== 'hidden';
  return {x: p.x, y: p.y, w: p.b.width, h: p.b.height, ready: shown && !el.disabled && p.onTop};
}"""
#: Whether the page draws: an animation frame within 2 s, else how long it waited.
_FRAME_PROBE = """() => new Promise((done) => {
  const t0 = performance.now();
  requestAnimationFrame(() => done(`a frame after ${Math.round(performance.now() - t0)} ms`));
  setTimeout(() => done('no animation frame in 2 s'), 2000);
})"""


def press(page, locator, count: int = 1, timeout: float = 60.0) -> None:
    """Press ``locator`` ``count`` times at its centre once it is visible, enabled, on top there and still (the
    same box in two reads 0.2 s apart), as a person clicks what they see. Unlike Playwright's checks, these need
    no drawn frame, so a press still lands while a loaded browser draws none."""
    deadline, last = time.monotonic() + timeout, None
    while True:
        at = locator.evaluate(_BUTTON_AT)
        if at["ready"] and at == last:
            break
        if time.monotonic() > deadline:
            raise AssertionError(
                f"{locator} was not visible, enabled, on top and still within {timeout:g} s: {at}"
            )
        last = at
        time.sleep(0.2)
    if count == 2:
        page.mouse.dblclick(at["x"], at["y"])
    else:
        page.mouse.click(at["x"], at["y"], click_count=count)


def _browser_load() -> str:
    """The Chromium processes using the most CPU now (``ps``), for a warning about a page that stopped drawing."""
    import subprocess

    try:
        out = subprocess.run(
            ["ps", "-C", "chromium", "-o", "pcpu=,rss=,args="], capture_output=True, text=True, timeout=5
        ).stdout
    except (OSError, subprocess.SubprocessError) as e:
        return f"ps failed: {e}"
    busiest = []
    for row in out.splitlines():
        cpu, _, args = [*row.split(None, 2), "", ""][:3]
        kind = next((a.removeprefix("--type=") for a in args.split() if a.startswith("--type=")), "browser")
        busiest.append((float(cpu or 0), kind))
    return ", ".join(f"{kind} {cpu:.0f} % CPU" for cpu, kind in sorted(busiest, reverse=True)[:4])


def click_button(page, locator, wait: float = 20.0) -> str | None:
    """Click ``locator`` with Playwright's checks; when they cannot pass within ``wait`` seconds, :func:`press` it
    instead and warn (so that the run's summary shows it). Returns None, or what Playwright waited for, the page's
    frames and the browser's processes when the checks did not pass (the warning's text)."""
    from playwright.sync_api import TimeoutError as PlaywrightTimeout

    try:
        locator.click(timeout=wait * 1000)
        return None
    except PlaywrightTimeout as e:
        log = [line.strip(" -") for line in str(e).splitlines() if line.strip(" -")]
        # what Playwright last said of the element when it gave up ("element is not stable", ...)
        waited = next(
            (line for line in reversed(log) if "element" in line), log[-1] if log else "no call log"
        )
        frames = str(page.evaluate(_FRAME_PROBE))
        load = _browser_load()
    press(page, locator)
    said = f"Playwright: {waited}; {frames}; {load}"
    warnings.warn(
        f"{locator}: Playwright's checks did not pass in {wait:g} s ({said}); pressed it", stacklevel=3
    )
    return said


def screen_point(page, client, point: np.ndarray) -> tuple[float, float]:
    """Where a world point appears on the page's canvas (viser cameras follow OpenCV: +z forward, +y down)."""
    import viser.transforms as vtf

    x0, y0, w, h = page.evaluate(
        "() => { const r = document.querySelector('canvas').getBoundingClientRect();"
        " return [r.x, r.y, r.width, r.height]; }"
    )
    cam = client.camera
    R = vtf.SO3(np.asarray(cam.wxyz)).as_matrix()
    p = R.T @ (np.asarray(point) - np.asarray(cam.position))
    f = (h / 2) / np.tan(cam.fov / 2)
    return x0 + w / 2 + f * p[0] / p[2], y0 + h / 2 + f * p[1] / p[2]


class ClickPerson:
    """A person recording with click-to-reach in one browser tab: every action a real browser event, counted.

    It reads the app only to know where things appear on the screen and whether the arm has arrived."""

    def __init__(self, page, tab):
        self.page, self.tab, self.tp = page, tab, tab.teleop
        self.actions: list[str] = []

    def state(self) -> str:
        frame = self.tp.client.latest_pose() if self.tp.client is not None else None
        return (
            f"status {self.tp.status.content!r}, tab actions {self.tab.actions}, recording {self.tp.recording}, "
            f"ee {None if frame is None else np.round(frame.ee_pos, 3)}"
        )

    def button(self, name: str) -> None:
        """Click a panel button as a person does: once the button is visible, still, enabled and on top (a forced
        click skips those checks and can land on whatever the panel just moved there)."""
        self.actions.append(name)
        click_button(self.page, self.page.get_by_role("button", name=name, exact=True))

    def move(self, name: str) -> np.ndarray:
        """Click a motion button (Down, Up, a nudge); returns where the app sends the gripper once it took it."""
        before, _ = self.tp.motion
        self.button(name)
        wait_until(lambda: self.tp.motion[0] > before, 20, f"{name} to be taken", self.state)
        goal = self.tp.motion[1]
        assert goal is not None
        return goal

    def click_at(self, world_point, what: str) -> None:
        """A left click on the canvas where ``world_point`` appears."""
        self.actions.append(f"click {what}")
        clicks = self.tp.clicks
        x, y = screen_point(self.page, self.tab.client, np.asarray(world_point, dtype=np.float64))
        self.page.mouse.click(x, y)
        wait_until(lambda: self.tp.clicks > clicks, 20, f"the click on {what} to reach the app", self.state)

    def ee(self) -> np.ndarray:
        return np.asarray(self.tp.client.latest_pose().ee_pos)

    def arrive(self, xy=None, z=None, what: str = "the arm to arrive") -> None:
        """Wait, as a person watches, until the grasp point is over ``xy`` and at height ``z`` (within 1 cm)."""

        def there() -> bool:
            ee = self.ee()
            return bool(
                (xy is None or np.linalg.norm(ee[:2] - np.asarray(xy)[:2]) < 0.01)
                and (z is None or abs(ee[2] - z) < 0.01)
            )

        wait_until(there, 30, what, self.state)

    def settle(self, ticks: int = 40) -> None:
        """Wait for the fingers to finish closing or opening (``ticks`` control ticks)."""
        start = self.tp.client.latest_pose().step
        wait_until(lambda: self.tp.client.latest_pose().step >= start + ticks, 20, "the fingers to move")

    def objects(self) -> dict[str, np.ndarray]:
        return self.tp.scene_model.object_positions(self.tp.latest_poses)

    def body(self, name: str) -> np.ndarray:
        return np.asarray(self.tp.latest_poses[self.tp.scene_model.geometry.body_names.index(name), :3])

    def record(self) -> None:
        tp = self.tp
        self.button("Record")
        wait_until(lambda: tp.recording, 30, "recording to start", self.state)
        self.page.get_by_text("● REC").filter(visible=True).first.wait_for(timeout=60_000)
        wait_until(lambda: tp.latest_poses is not None and tp.rest_known, 20, "the reset scene's poses")

    def stop_and_save(self) -> None:
        """Stop & save once the panel is recording; wait until the episode is stored."""
        tp = self.tp
        self.button("Stop & save")
        wait_until(
            lambda: not tp.status.content.startswith("Recording"), 30, "Stop & save to be taken", self.state
        )
        wait_until(lambda: tp.status.content.startswith("Saved"), 120, "the episode to be stored", self.state)

    # ------------------------------------------------------------------ demonstrations
    def pick_and_place(self, obj: str, zone: str) -> None:
        """Record, click the object, Down, Close, Up, click the zone, Down, Open, Stop & save."""
        self.record()
        p = self.objects()[f"obj_{obj}"]
        self.click_at(p + np.array([0.0, 0.0, 0.02]), f"the {obj}")
        self.arrive(p, what=f"the gripper over the {obj}")
        goal = self.move("Down")
        self.arrive(p, what="the grasp height", z=goal[2])
        self.button("Close")
        self.settle()
        goal = self.move("Up")
        self.arrive(z=goal[2], what="the carrying height")
        target = self.body(f"target_{zone}")
        self.click_at(target, f"the {zone} zone")
        self.arrive(target, what=f"the gripper over the {zone} zone")
        goal = self.move("Down")
        self.arrive(target, z=goal[2], what="the place height")
        self.button("Open")
        self.settle()
        wait_until(lambda: self.tp.success.value, 10, "the task's check to see the object placed", self.state)
        self.stop_and_save()

    def push(self, obj: str, direction: str) -> None:
        """Record, click the table behind the object, Close, Down, click the table beyond it, Stop & save."""
        self.record()
        p = self.objects()[f"obj_{obj}"]
        sign = 1.0 if direction == "forward" else -1.0
        behind = np.array([p[0], p[1] - sign * 0.1, 0.0])
        self.click_at(behind, f"the table behind the {obj} box")
        self.arrive(behind, what=f"the gripper behind the {obj} box")
        self.button("Close")
        goal = self.move("Down")
        self.arrive(z=goal[2], what="just above the table")
        beyond = np.array([p[0], p[1] + sign * 0.18, 0.0])
        self.click_at(beyond, f"the table beyond the {obj} box")
        self.arrive(beyond, what="the push to end")
        wait_until(lambda: self.tp.success.value, 10, "the task's check to see the box pushed", self.state)
        self.stop_and_save()

    def demonstrate(self, task: str) -> None:
        """The demonstration of ``task`` (``pick_place/OBJ->ZONE`` or ``push/OBJ-DIRECTION``)."""
        scene, name = task.split("/")
        if scene == "pick_place":
            obj, zone = name.split("->")
            self.pick_and_place(obj, zone)
        elif scene == "push":
            obj, direction = name.split("-")
            self.push(obj, direction)
        else:
            raise ValueError(f"no click script for {task!r}: pick_place and push tasks only")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--task", default="pick_place/cube->red", help="a pick_place or push task")
    parser.add_argument("--robot", default="sawyer", choices=("sawyer", "panda", "hand"))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0], help="one demonstration per scene seed")
    parser.add_argument(
        "--data-dir", default=None, help="keep the demonstrations here (default: a temporary one)"
    )
    parser.add_argument("--webgl", choices=tuple(WEBGL_ARGS), default="llvmpipe")
    parser.add_argument("--chromium", default=CHROMIUM, help="Chromium executable for Playwright")


def _choose(tab, task: str, robot: str, seed: int) -> None:
    """Set the panel's scene, robot, task and seed widgets and reopen the session (as a person's picks do)."""
    tp = tab.teleop
    scene = task.split("/")[0]
    if tp.scene.value != scene:
        tp.scene.value = scene
        tp.narrow_choices()
    tp.robot.value, tp.task.value, tp.seed.value = robot, task, seed
    tp.open()


def measure(args: argparse.Namespace) -> dict:
    os.environ.setdefault("MUJOCO_GL", "egl")
    from playwright.sync_api import sync_playwright

    from studio.backend import bus
    from studio.ui.app import StudioApp

    if not Path(args.chromium).exists():
        raise SystemExit(f"studio bench click-demo: {args.chromium} is missing (apt-get install chromium)")
    with tempfile.TemporaryDirectory(prefix="studio-bench-click-") as tmp:
        data_dir = Path(args.data_dir) if args.data_dir else Path(tmp) / "data"
        app = StudioApp(
            port=bus.free_loopback_port(),
            data_dir=data_dir,
            bus_config=bus.BusConfig.hub([bus.loopback_endpoint(bus.free_loopback_port())]),
        )
        demos: list[dict] = []
        try:
            if not app.wait_for_workers(120):
                raise SystemExit("studio bench click-demo: the embedded workers did not start")
            with sync_playwright() as p:
                browser = p.chromium.launch(
                    executable_path=args.chromium, args=CHROMIUM_ARGS + WEBGL_ARGS[args.webgl]
                )
                page = browser.new_page(viewport={"width": 1100, "height": 720})
                page.add_init_script(THROTTLE_RAF)
                t0 = time.perf_counter()
                page.goto(app.url)
                page.get_by_text("ready. Drag the gizmo").filter(visible=True).first.wait_for(timeout=120_000)
                ready = time.perf_counter() - t0
                (tab,) = app.tabs.values()
                first_saved = None
                for seed in args.seeds:
                    tp = tab.teleop
                    info = tp.info
                    if info is None or (info.task, info.robot, info.seed) != (args.task, args.robot, seed):
                        _choose(tab, args.task, args.robot, seed)
                    person = ClickPerson(page, tab)
                    before = {m.id for m in app.store.episodes()}
                    start = time.perf_counter()
                    person.demonstrate(args.task)
                    (meta,) = [m for m in app.store.episodes() if m.id not in before]
                    control_dt = tp.info.control_dt if tp.info is not None else 0.0
                    if meta.success and first_saved is None:
                        first_saved = time.perf_counter() - t0
                    demos.append(
                        {
                            "episode": meta.id,
                            "seed": seed,
                            "success": bool(meta.success),
                            "actions": len(person.actions),
                            "simulated_s": round(meta.num_steps * control_dt, 2),
                            "wall_s": round(time.perf_counter() - start, 2),
                        }
                    )
                browser.close()
        finally:
            app.stop()
        return {
            "task": args.task,
            "robot": args.robot,
            "page_ready_s": round(ready, 2),
            "seconds_to_first_saved": None if first_saved is None else round(first_saved, 2),
            "demonstrations": demos,
            "data_dir": str(data_dir) if args.data_dir else None,
        }
