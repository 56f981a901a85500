"""`studio bench ui`: the pose update rate a browser receives during teleop, and drag-to-motion latency.

Starts the studio in this process (hub, embedded workers, viser server) on free loopback ports with a
throwaway data directory, opens it in headless Chromium (Playwright; Debian's ``/usr/bin/chromium`` unless
``--chromium`` says otherwise) and, once the tab's teleop session is ready, drags the end-effector target
along a circle at ``--drag-hz`` through the gizmo's server-side callback — the path a browser drag takes.

Reported:

* ``browser_pose_frames_hz``: websocket frames per second that reach the page carrying body poses (each is
  applied at once by the browser), counted on the page's websocket and decoded as viser's wire format;
* ``browser_pose_messages_hz``: body pose messages per second inside those frames;
* ``server_pushes_hz``: pose batches the tab's pump handed to viser per second;
* ``drag_to_motion_ms_p50`` / ``_p99``: from the drag reaching the server to the first pose frame back from
  the sim worker that applied it (IK and physics on the worker, the bus both ways);
* ``drag_to_push_ms_p50`` / ``_p99``: to the moment that frame's poses were queued for the browser;
* ``browser_frames_hz``: frames the page drew per second (viser draws on demand: after each change, for a
  short settle window, and once a second);
* ``browser_cpu_pct``: CPU time of all of Chromium's processes during the drag, in % of one core (100 = one core
  busy). Without a GPU the page's WebGL runs on the CPU (SwiftShader) and every pose frame is a redraw, so this is
  the cost of showing the scene (``--scene``, ``--max-faces``), next to ``scene_faces``, the triangles shown.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]
#: WebGL without a GPU, by backend. Chromium's default is SwiftShader (``--disable-gpu``); Mesa's llvmpipe
#: through ANGLE's EGL backend (the libEGL the studio installs for MuJoCo) draws the studio's scene at about a
#: third of SwiftShader's CPU per frame on these machines (docs/ui.md, `studio bench ui --webgl ...`).
WEBGL_ARGS = {
    "llvmpipe": ["--use-gl=angle", "--use-angle=gl-egl", "--ignore-gpu-blocklist"],
    "swiftshader": ["--disable-gpu"],
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seconds", type=float, default=8.0, help="length of the measured drag")
    parser.add_argument("--drag-hz", type=float, default=60.0, help="gizmo updates per second")
    parser.add_argument("--robot", default="sawyer", choices=("sawyer", "panda"))
    parser.add_argument("--scene", default="pick_place", help="pick_place, push or metaworld (the Sawyer)")
    parser.add_argument(
        "--max-faces",
        type=int,
        default=None,
        help="triangle budget per mesh in the browser (default: the studio's, scene_view.MAX_FACES; "
        "0 = the scene's own meshes)",
    )
    parser.add_argument(
        "--dpr",
        type=float,
        default=None,
        help="fixed canvas pixel ratio (viser's fixedDpr URL parameter; default: viser's adaptive one)",
    )
    parser.add_argument(
        "--pose-hz",
        type=float,
        default=None,
        help="cap on pose frames per second to a tab (default: the studio's, app.MAX_POSE_HZ)",
    )
    parser.add_argument(
        "--webgl",
        choices=tuple(WEBGL_ARGS),
        default="llvmpipe",
        help="software WebGL backend of the headless browser",
    )
    parser.add_argument("--chromium", default=CHROMIUM, help="Chromium executable for Playwright")


class _FrameCounter:
    """Decodes viser websocket frames in the page and counts those that carry body poses."""

    def __init__(self, prefix: str = "/sim/b"):
        import zstandard

        self.prefix = prefix
        self._zstd = zstandard.ZstdDecompressor()
        self.counting = False
        self.frames = 0
        self.messages = 0
        self._lock = threading.Lock()

    def __call__(self, payload) -> None:
        if not self.counting or isinstance(payload, str):
            return
        import msgspec

        data = bytes(payload)
        try:
            size = int.from_bytes(data[:8], "little")
            csize = int.from_bytes(data[8:16], "little")
            inner = msgspec.msgpack.decode(self._zstd.decompress(data[16 : 16 + csize], max_output_size=size))
        except Exception:
            return
        n = sum(
            1
            for m in inner.get("messages", ())
            if m.get("type") in ("SetPositionMessage", "SetOrientationMessage")
            and str(m.get("name", "")).startswith(self.prefix)
        )
        if n:
            with self._lock:
                self.frames += 1
                self.messages += n


WEBGL_RENDERER_JS = """(() => { const gl = document.createElement('canvas').getContext('webgl2');
  if (!gl) return null; const info = gl.getExtension('WEBGL_debug_renderer_info');
  return info ? gl.getParameter(info.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER); })()"""


COUNT_FRAMES_JS = """(() => { window.__studioFrames = 0; const raf = window.requestAnimationFrame.bind(window);
  window.requestAnimationFrame = (cb) => raf((t) => { window.__studioFrames++; cb(t); }); })();"""


def _until(ready, timeout: float, what: str):
    deadline = time.monotonic() + timeout
    while not (value := ready()):
        if time.monotonic() > deadline:
            raise SystemExit(f"studio bench ui: timed out waiting for {what}")
        time.sleep(0.1)
    return value


def _percentiles(values: list[float]) -> tuple[float | None, float | None]:
    if not values:
        return None, None
    arr = np.asarray(values)
    return float(np.percentile(arr, 50)), float(np.percentile(arr, 99))


def _descendants_cpu_s(root: int, names: tuple[str, ...] = ("chromium", "chrome")) -> float:
    """User + system CPU seconds of the processes below ``root`` whose command name starts with one of ``names``."""
    parents: dict[int, int] = {}
    comms: dict[int, str] = {}
    times: dict[int, float] = {}
    tick = os.sysconf("SC_CLK_TCK")
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        comm = stat[stat.index("(") + 1 : stat.rindex(")")]
        fields = stat[stat.rindex(")") + 2 :].split()
        pid = int(entry.name)
        parents[pid], comms[pid] = int(fields[1]), comm
        times[pid] = (int(fields[11]) + int(fields[12])) / tick
    total = 0.0
    for pid, comm in comms.items():
        if not comm.startswith(names):
            continue
        p = pid
        while p > 1 and p != root:
            p = parents.get(p, 0)
        if p == root:
            total += times[pid]
    return total


def measure(args: argparse.Namespace) -> dict:
    os.environ.setdefault("MUJOCO_GL", "egl")
    from playwright.sync_api import sync_playwright

    from studio.backend import bus
    from studio.ui import app as app_module
    from studio.ui import scene_view
    from studio.ui.app import StudioApp

    if not Path(args.chromium).exists():
        raise SystemExit(f"studio bench ui: {args.chromium} is missing (apt-get install chromium)")
    if args.scene == "metaworld" and args.robot != "sawyer":
        raise SystemExit("studio bench ui: Meta-World scenes have the Sawyer only (--robot sawyer)")
    if args.pose_hz is not None:
        app_module.MAX_POSE_HZ = args.pose_hz
    if args.max_faces is not None:
        scene_view.MAX_FACES = args.max_faces or None
    with tempfile.TemporaryDirectory(prefix="studio-bench-ui-") as tmp:
        app = StudioApp(
            port=bus.free_loopback_port(),
            data_dir=Path(tmp) / "data",
            bus_config=bus.BusConfig.hub([bus.loopback_endpoint(bus.free_loopback_port())]),
        )
        try:
            if not app.wait_for_workers(120):
                raise SystemExit("studio bench ui: the embedded workers did not start")
            counter = _FrameCounter()
            with sync_playwright() as p:
                browser = p.chromium.launch(
                    executable_path=args.chromium, args=CHROMIUM_ARGS + WEBGL_ARGS[args.webgl]
                )
                page = browser.new_page(viewport={"width": 1100, "height": 720})
                page.on("websocket", lambda ws: ws.on("framereceived", counter))
                page.add_init_script(COUNT_FRAMES_JS)
                page.goto(app.url + ("" if args.dpr is None else f"?fixedDpr={args.dpr:g}"))
                page.get_by_text("ready. Drag the gizmo").filter(visible=True).first.wait_for(timeout=120_000)
                renderer = page.evaluate(WEBGL_RENDERER_JS)
                (tab,) = app.tabs.values()
                teleop = tab.teleop
                if (args.scene, args.robot) != (teleop.scene.value, teleop.robot.value):
                    if args.scene not in teleop.scene.options:
                        raise SystemExit(
                            f"studio bench ui: unknown scene {args.scene!r}; "
                            f"choose from {teleop.scene.options}"
                        )
                    teleop.scene.value = args.scene
                    teleop.narrow_choices()
                    teleop.robot.value = args.robot
                    teleop.open()
                    _until(
                        lambda: teleop.info is not None and teleop.info.scene == args.scene,
                        180,
                        "the session",
                    )
                faces = tab.view.faces_shown
                pose = teleop.client.latest_pose() if teleop.client is not None else None
                if pose is None:
                    raise RuntimeError("the teleop session is open but has sent no pose")
                center = np.asarray(pose.ee_pos, dtype=np.float64)
                time.sleep(1.0)
                app.stats.reset()
                pushes0 = tab.pose_pushes
                sent = [0]

                def drag() -> None:  # the gizmo's callback at drag rate, on its own thread like viser's
                    period = 1.0 / args.drag_hz
                    start = time.perf_counter()
                    while (now := time.perf_counter()) - start < args.seconds:
                        phase = 2 * np.pi * (now - start) / 4.0  # one circle every 4 s, 6 cm radius
                        teleop.move_to(center + 0.06 * np.array([np.cos(phase) - 1.0, np.sin(phase), 0.0]))
                        sent[0] += 1
                        time.sleep(max(0.0, start + sent[0] * period - time.perf_counter()))

                dragger = threading.Thread(target=drag, daemon=True)
                counter.counting = True
                t0 = time.perf_counter()
                cpu0 = _descendants_cpu_s(os.getpid())
                frames0 = page.evaluate("window.__studioFrames")
                dragger.start()
                while dragger.is_alive():
                    page.wait_for_timeout(50)  # Playwright delivers websocket events while it runs
                elapsed = time.perf_counter() - t0
                cpu = _descendants_cpu_s(os.getpid()) - cpu0
                frames = page.evaluate("window.__studioFrames") - frames0
                page.wait_for_timeout(300)  # frames in flight
                counter.counting = False
                k = sent[0]
                pushes = tab.pose_pushes - pushes0
                browser.close()
            ack50, ack99 = _percentiles(app.stats.ack_ms)
            push50, push99 = _percentiles(app.stats.push_ms)
            return {
                "seconds": round(elapsed, 2),
                "scene": args.scene,
                "robot": args.robot,
                "max_faces_per_mesh": scene_view.MAX_FACES,
                "dpr": args.dpr,
                "max_pose_hz": app_module.MAX_POSE_HZ,
                "scene_faces": faces,
                "webgl": renderer,
                "browser_frames_hz": round(frames / elapsed, 1),
                "browser_cpu_pct": round(100 * cpu / elapsed, 1),
                "drag_hz": args.drag_hz,
                "drags_sent": k,
                "browser_pose_frames_hz": round(counter.frames / elapsed, 1),
                "browser_pose_messages_hz": round(counter.messages / elapsed, 1),
                "server_pushes_hz": round(pushes / elapsed, 1),
                "drag_to_motion_ms_p50": None if ack50 is None else round(ack50, 2),
                "drag_to_motion_ms_p99": None if ack99 is None else round(ack99, 2),
                "drag_to_push_ms_p50": None if push50 is None else round(push50, 2),
                "drag_to_push_ms_p99": None if push99 is None else round(push99, 2),
                "samples": len(app.stats.ack_ms),
            }
        finally:
            app.stop()
