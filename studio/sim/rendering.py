"""Offscreen renderers for observation cameras: fast settings, one GL context each, closed before exit.

Observation cameras render with shadows, reflections, skybox and multisampling off (multisampling is
``offsamples`` in the model, set by our scenes): on CPU (llvmpipe) that is 20–40× faster than MuJoCo's
defaults. Two process-wide hazards live here too:

* Triton (torch's kernel compiler) and Mesa's software EGL both carry LLVM; importing triton *after* an EGL
  context exists segfaults the process (torchvision imports it through ``torch._dynamo``). ``new_renderer``
  therefore imports triton, when installed, before the first context — 0.24 s once per process.
* Renderers still alive when the interpreter exits must be closed before MuJoCo tears its display down;
  environments register themselves with ``track`` and are closed by an exit hook registered after the first
  context (``atexit`` runs hooks last-in, first-out).
"""

from __future__ import annotations

import atexit
import weakref

import mujoco
import numpy as np

_LIVE: weakref.WeakSet = weakref.WeakSet()
_state = {"exit_hook": False, "llvm_preloaded": False}


def preload_llvm_users() -> None:
    """Import triton before any EGL context exists (see the module docstring); a no-op without triton."""
    if _state["llvm_preloaded"]:
        return
    _state["llvm_preloaded"] = True
    try:
        import triton  # noqa: F401
    except Exception:  # not installed (CPU-only wheels) or broken: nothing to protect against
        pass


def track(owner) -> None:
    """Close ``owner`` (anything with ``close()``) at interpreter exit if it is still alive then."""
    _LIVE.add(owner)


def _close_all() -> None:
    for owner in list(_LIVE):
        owner.close()


def new_renderer(model: mujoco.MjModel, height: int, width: int, depth: bool = False) -> mujoco.Renderer:
    """An RGB (or depth) renderer of ``height``×``width`` with the fast observation settings."""
    preload_llvm_users()
    vis = model.vis.global_
    vis.offwidth, vis.offheight = max(vis.offwidth, width), max(vis.offheight, height)
    r = mujoco.Renderer(model, height, width)
    if depth:
        r.enable_depth_rendering()
    for flag in (
        mujoco.mjtRndFlag.mjRND_SHADOW,
        mujoco.mjtRndFlag.mjRND_REFLECTION,
        mujoco.mjtRndFlag.mjRND_SKYBOX,
    ):
        r.scene.flags[flag] = False
    if not _state["exit_hook"]:
        atexit.register(_close_all)
        _state["exit_hook"] = True
    return r


class Renderers:
    """The renderers of one model, one per (height, width, depth) and created on first use."""

    def __init__(self, model: mujoco.MjModel) -> None:
        self.model = model
        self._by_size: dict[tuple[int, int, bool], mujoco.Renderer] = {}

    def render(
        self,
        data: mujoco.MjData,
        camera: int | str,
        size: tuple[int, int],
        *,
        depth: bool = False,
        scene_option: mujoco.MjvOption | None = None,
    ):
        """RGB (H, W, 3) uint8, or depth (H, W) float32 in metres, from ``camera``."""
        key = (int(size[0]), int(size[1]), depth)
        r = self._by_size.get(key)
        if r is None:
            r = self._by_size[key] = new_renderer(self.model, key[0], key[1], depth)
        r.update_scene(data, camera=camera, scene_option=scene_option)
        return r.render().astype(np.float32) if depth else r.render().copy()

    def close(self) -> None:
        for r in self._by_size.values():
            r.close()
        self._by_size.clear()
