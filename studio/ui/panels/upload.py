"""Upload a human video: import it (errors as notifications), show the 10 frames the model will see, pick the
task, save it as an expert demonstration.

Importing is :func:`studio.data.video_import.load_human_video`, the same code as ``studio import-video``:
everything is checked and decoded before the store is touched, so a rejected file writes nothing. The
browser shows the transfer's progress itself; decoding shows a progress bar here.
"""

from __future__ import annotations

import logging
import re
import tempfile
from pathlib import Path

import numpy as np

from studio.backend.plan_job import expert_indices
from studio.data.episode import scene_of_task
from studio.data.video_import import FIT_MODES, VideoImportError, load_human_video
from studio.sim.tasks import list_tasks
from studio.ui.images import filmstrip

log = logging.getLogger("studio.ui.upload")

#: Uploads keep at most this many frames per second (thinned by timestamp, whole frames only).
UPLOAD_FPS_CAP = 15.0

HINT = """Upload a video of **a person doing the task** (MP4, WebM, MOV…, up to 2 min). It is checked and
normalised to the studio's frame size; below you see the **10 frames the model will look at**. Pick the
task it shows and save it as an expert demonstration for *Imitate*."""


def describe_import(name: str, meta) -> str:
    """What an imported video became, saying so when its frame rate was lowered."""
    text = f"`{name}`: {meta.num_frames} frames at {meta.fps:.0f} fps"
    source = float(meta.extra.get("source_fps") or 0.0)
    if source > 0 and abs(source - meta.fps) > 0.5:
        text += f" (resampled from the video's {source:.0f} fps: uploads keep at most {UPLOAD_FPS_CAP:.0f} a second)"
    return f"{text}, {meta.width}×{meta.height}, {meta.extra.get('fit', 'letterbox')}."


class UploadPanel:
    """The *Upload* tab."""

    def __init__(self, tab):
        self.tab = tab
        self.pending = None
        gui = tab.client.gui
        gui.add_markdown(HINT)
        tasks = [t for t in list_tasks() if not t.startswith("metaworld/")] + [
            t for t in list_tasks() if t.startswith("metaworld/")
        ]
        self.task = gui.add_dropdown("Task shown", tuple(tasks), initial_value=tasks[0])
        self.fit = gui.add_dropdown(
            "Fit",
            FIT_MODES,
            initial_value=FIT_MODES[0],
            hint="letterbox keeps everything (black bars); crop fills the frame (edges lost)",
        )
        self.button = gui.add_upload_button("Upload a video…", icon="upload", mime_type="video/*")
        self.progress = gui.add_progress_bar(0.0, animated=True, visible=False)
        self.status = gui.add_markdown("")
        self.strip = gui.add_image(
            np.full((40, 200, 3), 255, np.uint8), label="The 10 frames the model will see", visible=False
        )
        self.save = gui.add_button("Save as expert demonstration", color="green", disabled=True)
        self.drop = gui.add_button("Discard upload", disabled=True)
        self.button.on_upload(self._on_upload)
        self.save.on_click(lambda _: tab.run(self.store_pending, "saving the demonstration"))
        self.drop.on_click(lambda _: self._clear("Upload discarded."))

    def _on_upload(self, event) -> None:
        file = event.target.value
        name, content = file.name, file.content
        self.tab.run(lambda: self.import_bytes(name, content), f"importing {name}")

    def import_bytes(self, name: str, content: bytes) -> bool:
        """Check and decode an uploaded file; on success show its filmstrip and wait for *Save*."""
        safe = re.sub(r"[^A-Za-z0-9_.-]", "_", Path(name).name)[:120] or "upload"
        self._clear("")
        self.progress.visible = True
        self.progress.value = 100.0
        self.status.content = f"Importing `{name}` ({len(content) / 2**20:.1f} MB)…"
        try:
            with tempfile.TemporaryDirectory(prefix="studio-upload-") as tmp:
                path = Path(tmp) / safe
                path.write_bytes(content)
                episode = load_human_video(path, self.task.value, fit=self.fit.value, fps_cap=UPLOAD_FPS_CAP)
        except VideoImportError as e:
            log.info("upload %s rejected: %s%s", name, e, f" ({e.detail})" if e.detail else "")
            return self._reject(str(e))
        except Exception:
            log.exception("upload %s: the import failed", name)
            return self._reject(
                f"{name} could not be imported because of an error in the studio (see its log)."
            )
        finally:
            self.progress.visible = False
        self.pending = episode
        frames = episode.frames
        idx = expert_indices(len(frames), 10)
        self.strip.image = filmstrip(
            frames[idx], cols=5, height=72, labels=[str(i + 1) for i in range(len(idx))]
        )
        self.strip.visible = True
        self.save.disabled = False
        self.drop.disabled = False
        self.status.content = f"{describe_import(name, episode.meta)} Check the task above, then **Save**."
        return True

    def _reject(self, sentence: str) -> bool:
        self.progress.visible = False
        self.status.content = f"**Rejected:** {sentence}"
        self.tab.notify("Video rejected", sentence, error=True)
        return False

    def store_pending(self) -> str | None:
        episode = self.pending
        if episode is None:
            return None
        task = self.task.value
        episode = episode.with_meta(task=task, scene=scene_of_task(task))
        meta = self.tab.app.store.add_episode(episode)
        self.tab.app.dataset_changed()
        self._clear(f"Saved `{meta.id}` as an expert demonstration of **{task}**.")
        self.tab.notify("Demonstration saved", f"{task}: {meta.id}")
        return meta.id

    def _clear(self, text: str) -> None:
        self.pending = None
        self.strip.visible = False
        self.save.disabled = True
        self.drop.disabled = True
        self.status.content = text

    def refresh(self) -> None:
        pass

    def close(self) -> None:
        pass
