"""A timeline control: a slider over N positions with a Play / Pause button that advances it in real time."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable


class Timeline:
    """Slider + play button. ``on_change(index)`` runs for every position shown (user drags and playback).

    The slider's range is set with :meth:`reset`; playback runs on its own thread at ``fps`` positions
    per second and stops at the end.
    """

    def __init__(self, gui, label: str, on_change: Callable[[int], None], fps: float = 10.0):
        self.on_change = on_change
        self.fps = fps
        self.slider = gui.add_slider(label, min=0, max=1, step=1, initial_value=0, disabled=True)
        self.play = gui.add_button_group("Playback", ("Play", "Pause"))
        self._playing = threading.Event()
        self._closed = False
        self._thread: threading.Thread | None = None
        self.slider.on_update(lambda e: self.on_change(int(self.slider.value)))
        self.play.on_click(lambda e: self.start() if e.target.value == "Play" else self._playing.clear())

    def reset(self, n: int, fps: float | None = None) -> None:
        self._playing.clear()
        if fps:
            self.fps = fps
        self.slider.max = max(1, n - 1)
        self.slider.disabled = n < 2
        if self.slider.value != 0:
            self.slider.value = 0  # calls on_change
        else:
            self.on_change(0)

    def start(self) -> None:
        if self.slider.disabled:
            return
        if int(self.slider.value) >= int(self.slider.max):
            self.slider.value = 0
        self._playing.set()
        if self._thread is None or not self._thread.is_alive():
            self._thread = threading.Thread(target=self._run, daemon=True, name="timeline")
            self._thread.start()

    def _run(self) -> None:
        while not self._closed:
            time.sleep(1.0 / max(self.fps, 1e-3))
            if not self._playing.is_set() or self._closed:
                return
            nxt = int(self.slider.value) + 1
            if nxt > int(self.slider.max):
                self._playing.clear()
                return
            self.slider.value = nxt

    def close(self) -> None:
        self._closed = True
        self._playing.clear()
