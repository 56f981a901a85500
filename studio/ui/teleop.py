"""A teleoperation session: one simulated scene driven by a Cartesian target, recorded on demand.

The session runs its own control loop in a thread at the simulator's control rate, so the arm moves
smoothly however irregularly the browser sends gizmo updates (the latest target wins). Recording keeps
full-rate arrays and renders frames when it stops (:class:`studio.sim.recorder.Recorder`). Everything
that touches the GL context (rendering) runs on the loop thread, since EGL contexts belong to the
thread that created them; other threads hand such work over with :meth:`TeleopSession.call`.
"""

from __future__ import annotations

import queue
import threading
import time
from concurrent.futures import Future

import numpy as np

from studio.sim.env import make_env
from studio.sim.recorder import Recorder
from studio.sim.recording import Recording


class TeleopSession:
    """One browser client's scene. Every method is thread-safe."""

    def __init__(self, scene: str, robot: str, task: str, seed: int, on_tick=None):
        self.lock = threading.Lock()
        self.env = make_env(scene, robot)  # a SimEnv, or a MetaWorldEnv for scene 'metaworld'
        self.env.reset(task, seed)
        self.target = self.env.ee_pos.copy()
        self.gripper = 0.0
        self.recorder: Recorder | None = None
        self.on_tick = on_tick
        self._calls: queue.Queue = queue.Queue()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="teleop-loop", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ loop
    def _loop(self) -> None:
        dt = self.env.control_dt
        next_t = time.perf_counter()
        while not self._stop.is_set():
            with self.lock:
                self.env.step(self.target, self.gripper)
                if self.recorder is not None:
                    self.recorder.tick()
            while not self._calls.empty():
                fn, fut = self._calls.get_nowait()
                try:
                    with self.lock:
                        fut.set_result(fn())
                except Exception as e:  # handed back to the caller
                    fut.set_exception(e)
            if self.on_tick is not None:
                self.on_tick(self)
            next_t += dt
            delay = next_t - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
            else:
                next_t = time.perf_counter()  # fell behind: do not try to catch up in a burst

    def call(self, fn, timeout: float = 30.0):
        """Run ``fn()`` on the loop thread (holding the lock) and return its result."""
        fut: Future = Future()
        self._calls.put((fn, fut))
        return fut.result(timeout=timeout)

    # ------------------------------------------------------------------ commands
    def set_target(self, position) -> None:
        p = np.asarray(position, dtype=np.float64).reshape(3)
        if np.all(np.isfinite(p)):
            with self.lock:
                self.target = p

    def set_gripper(self, closed: float) -> None:
        with self.lock:
            self.gripper = float(np.clip(closed, 0.0, 1.0))

    def reset(self, task: str | None = None, seed: int | None = None) -> None:
        with self.lock:
            self.env.reset(task or self.env.task.name, self.env.seed if seed is None else seed)
            self.target = self.env.ee_pos.copy()
            self.gripper = 0.0
            self.recorder = None

    def start_recording(self) -> None:
        with self.lock:
            self.recorder = Recorder(self.env)
            self.recorder.tick()

    @property
    def recording(self) -> bool:
        return self.recorder is not None

    def stop_recording(self, n_frames: int = 30) -> Recording | None:
        """Stop and return the recording (frames rendered now), or None if nothing was recorded."""
        with self.lock:
            rec, self.recorder = self.recorder, None
        if rec is None or len(rec) < 2:
            return None
        return self.call(lambda: rec.finish(n_frames=n_frames))

    def discard_recording(self) -> None:
        with self.lock:
            self.recorder = None

    def render(self, size=(120, 160)) -> np.ndarray:
        return self.call(lambda: self.env.render(size=size))

    def close(self) -> None:
        try:
            self.call(self.env.close, timeout=5.0)
        finally:
            self._stop.set()
            self._thread.join(timeout=2.0)
