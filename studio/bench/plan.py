"""`studio bench plan`: where does a checkpoint grasp and release, and does that depend on the agent's scene?

Success rates say *that* a policy fails; this says *how*, in a minute and without simulating a rollout. For each
pick-and-place task (training or held-out), the last ``--scenes`` stored agent episodes give first frames with
known object positions; each is planned with a random stored expert demonstration of the same task (the grasp is
the first waypoint whose gripper flag is closed, ``studio.sim.waypoints.gripper_flags``, the release the first
open one after it). Reported, per task and over all:

* ``right_object`` — the task's object is the nearest object to the grasp point (chance: one over the number of
  objects). This is the object matching that one-shot imitation needs: objects are shuffled in every scene.
* ``grasp_err_m`` — median distance (xy) from the grasp point to the task's object in the agent's scene.
* ``grasp_to_demo_object_m`` — median distance from the grasp point to where that object lay *in the
  demonstration*: small values with a large ``grasp_err_m`` mean "grasp where the demonstration grasped".
* ``release_err_m`` — median distance from the release point to where the agent's scripted expert released.
* ``scene_dependence`` — one demonstration planned against every scene: the spread (std, xy) of the grasp point
  divided by the spread of the task's object over those scenes. 1 when the grasp follows the object, 0 when the
  plan ignores the agent's frame (the failure docs/experiments.md first measured by hand).
* ``named`` — for a checkpoint trained with the demonstration-task loss (``demo_task``), what its head calls the
  demonstrations used, counted: a training task's name, or the object and the target. On a held-out task it
  shows whether the demonstration was read as its own parts or as the nearest training task.

``--mirror`` flips the demonstrations left–right first: our tasks are named by colour, so a mirrored video still
demonstrates its task, but copying its grasp and release places becomes wrong (``train.expert_hflip``). The
tabletop camera sits in the x = 0 plane without roll, so the mirrored video shows the world reflected x → −x, and
``grasp_to_demo_object_m`` is measured to the reflected place.
"""

from __future__ import annotations

import argparse
import time
from collections import Counter

import numpy as np


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--checkpoint", required=True, help="checkpoint or policy file")
    parser.add_argument(
        "--data-dir", required=True, help="episode store with Sawyer experts and Panda agents"
    )
    parser.add_argument("--scene", default="pick_place", help="scene whose split names the tasks")
    parser.add_argument("--tasks", default="held-out", help="held-out | train | comma-separated task names")
    parser.add_argument("--scenes", type=int, default=12, help="agent episodes (scenes) per task")
    parser.add_argument("--mirror", action="store_true", help="mirror the demonstrations left-right")
    parser.add_argument("--seed", type=int, default=0, help="seed of the demonstration draw")
    parser.add_argument("--threads", type=int, default=1)


def task_object(task: str) -> str:
    """``pick_place/cube->red`` → ``cube``; other task names have no single object to match."""
    _, _, name = task.partition("/")
    obj, arrow, _ = name.partition("->")
    if not arrow or not obj:
        raise SystemExit(f"studio bench plan: task {task!r} is not of the form scene/object->target")
    return obj


def grasp_and_release(waypoints: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None]:
    """xy of the first closed waypoint and of the first open waypoint after it (None where there is none)."""
    from studio.sim.waypoints import gripper_flags

    flags = gripper_flags(waypoints)
    closed = np.flatnonzero(flags)
    if not len(closed):
        return None, None
    opened = [i for i in range(closed[0] + 1, len(waypoints)) if not flags[i]]
    return waypoints[closed[0], :2], (waypoints[opened[0], :2] if opened else None)


def scripted_release(arrays: dict) -> np.ndarray | None:
    """xy of the end effector when the agent episode's scripted expert opened the gripper after closing it."""
    closed = np.asarray(arrays["gripper_cmd"]) > 0.5
    steps = np.flatnonzero(closed[:-1] & ~closed[1:])
    return None if not len(steps) else np.asarray(arrays["ee_pos_world"])[steps[0] + 1, :2]


def _median(values: list) -> float | None:
    vals = [v for v in values if v is not None and np.isfinite(v)]
    return round(float(np.median(vals)), 4) if vals else None


def _demonstration(store, meta, obj: str, mirror: bool, cache: dict) -> tuple[np.ndarray, np.ndarray]:
    """A demonstration's frames (mirrored if asked) and the xy where its object lay as the video shows it."""
    if meta.id not in cache:
        frames = store.load_frames(meta.id)
        frames = np.ascontiguousarray(frames[:, :, ::-1]) if mirror else frames
        objects = store.load_arrays(meta.id)[2]["object_poses"][0]
        where = np.array(objects[list(meta.object_names).index(obj), :2], dtype=np.float64)
        if mirror:  # the camera looks along the x = 0 plane: an image mirror is x -> -x
            where[0] = -where[0]
        cache[meta.id] = (frames, where)
    return cache[meta.id]


def measure(args: argparse.Namespace) -> dict:
    import torch

    from studio.data.splits import resolve_tasks
    from studio.data.store import EpisodeStore
    from studio.model.planner import Planner

    torch.set_num_threads(args.threads)
    tasks = resolve_tasks(args.scene, args.tasks)
    planner = Planner.load(args.checkpoint)
    rng = np.random.default_rng(args.seed)
    t0 = time.perf_counter()
    per_task: dict[str, dict] = {}
    every: dict[str, list] = {"right": [], "grasp": [], "demo": [], "release": [], "dependence": []}
    n_objects = 0
    with EpisodeStore(args.data_dir) as store:
        for task in tasks:
            obj = task_object(task)
            agents = store.episodes(task=task, role="agent")[-args.scenes :]
            experts = store.episodes(task=task, role="expert")
            if not agents or not experts:
                raise SystemExit(
                    f"studio bench plan: {task!r} needs stored agent and expert episodes in "
                    f"{args.data_dir} (studio collect --robot panda / --robot sawyer)"
                )
            demos: dict[str, tuple] = {}

            def plan(expert_meta, agent, demos=demos, obj=obj):
                frames, _ = _demonstration(store, expert_meta, obj, args.mirror, demos)
                cam = agent.camera
                return planner.plan(frames, agent.frames[0], cam.K, cam.T_world_cam).waypoints_world

            rows: dict[str, list] = {"right": [], "grasp": [], "demo": [], "release": []}
            named: Counter[str] = Counter()
            fixed_grasps, fixed_objects = [], []
            for meta in agents:
                agent = store.load(meta.id)
                objects = np.asarray(agent.arrays["object_poses"][0])[:, :2]
                target = objects[list(meta.object_names).index(obj)]
                expert_meta = experts[int(rng.integers(len(experts)))]
                grasp, release = grasp_and_release(plan(expert_meta, agent))
                frames, demo_object = _demonstration(store, expert_meta, obj, args.mirror, demos)
                name = planner.name_demonstration(frames)
                if name is not None:
                    named[", ".join(name)] += 1
                if grasp is None:
                    rows["right"].append(False)
                    rows["grasp"].append(None)
                    rows["demo"].append(None)
                else:
                    nearest = int(np.argmin(np.linalg.norm(objects - grasp, axis=1)))
                    rows["right"].append(nearest == list(meta.object_names).index(obj))
                    rows["grasp"].append(float(np.linalg.norm(target - grasp)))
                    rows["demo"].append(float(np.linalg.norm(demo_object - grasp)))
                scripted = scripted_release(agent.arrays)
                if release is None or scripted is None:
                    rows["release"].append(None)
                else:
                    rows["release"].append(float(np.linalg.norm(release - scripted)))
                fixed, _ = grasp_and_release(plan(experts[0], agent))
                if fixed is not None:
                    fixed_grasps.append(fixed)
                    fixed_objects.append(target)
            dependence = None
            if len(fixed_grasps) >= 2:
                spread_obj = float(np.linalg.norm(np.std(fixed_objects, axis=0)))
                spread_grasp = float(np.linalg.norm(np.std(fixed_grasps, axis=0)))
                dependence = round(spread_grasp / spread_obj, 3) if spread_obj > 1e-6 else None
            per_task[task] = {
                "scenes": len(agents),
                "right_object": round(float(np.mean(rows["right"])), 3),
                "grasp_err_m": _median(rows["grasp"]),
                "grasp_to_demo_object_m": _median(rows["demo"]),
                "release_err_m": _median(rows["release"]),
                "scene_dependence": dependence,
                **({"named": dict(named.most_common())} if named else {}),
            }
            for key in ("right", "grasp", "demo", "release"):
                every[key] += rows[key]
            every["dependence"].append(dependence)
            n_objects = len(agents[0].object_names)
    return {
        "checkpoint": args.checkpoint,
        "tasks": per_task,
        "mirror": args.mirror,
        "chance_right_object": round(1.0 / n_objects, 3) if n_objects else None,
        "right_object": round(float(np.mean(every["right"])), 3),
        "grasp_err_m": _median(every["grasp"]),
        "grasp_to_demo_object_m": _median(every["demo"]),
        "release_err_m": _median(every["release"]),
        "scene_dependence": _median(every["dependence"]),
        "wall_s": round(time.perf_counter() - t0, 1),
    }
