"""The Meta-World task family: the 50 Sawyer tasks of the installed ``metaworld`` package, by name.

Our names are ``metaworld/<v3 name>``, e.g. ``metaworld/button-press-v3``. The list is written out here
(instead of read from ``metaworld.env_dict``) so that listing tasks never imports Meta-World; a test
checks it against the installed package. Everything that needs the simulator lives in
:mod:`studio.sim.metaworld_env`.
"""

from __future__ import annotations

from dataclasses import dataclass

SCENE = "metaworld"

#: Meta-World v3 environment names, in the order of ``metaworld.env_dict.ALL_V3_ENVIRONMENTS``.
ENV_NAMES: tuple[str, ...] = (
    "assembly-v3",
    "basketball-v3",
    "bin-picking-v3",
    "box-close-v3",
    "button-press-topdown-v3",
    "button-press-topdown-wall-v3",
    "button-press-v3",
    "button-press-wall-v3",
    "coffee-button-v3",
    "coffee-pull-v3",
    "coffee-push-v3",
    "dial-turn-v3",
    "disassemble-v3",
    "door-close-v3",
    "door-lock-v3",
    "door-open-v3",
    "door-unlock-v3",
    "hand-insert-v3",
    "drawer-close-v3",
    "drawer-open-v3",
    "faucet-open-v3",
    "faucet-close-v3",
    "hammer-v3",
    "handle-press-side-v3",
    "handle-press-v3",
    "handle-pull-side-v3",
    "handle-pull-v3",
    "lever-pull-v3",
    "pick-place-wall-v3",
    "pick-out-of-hole-v3",
    "pick-place-v3",
    "plate-slide-v3",
    "plate-slide-side-v3",
    "plate-slide-back-v3",
    "plate-slide-back-side-v3",
    "peg-insert-side-v3",
    "peg-unplug-side-v3",
    "soccer-v3",
    "stick-push-v3",
    "stick-pull-v3",
    "push-v3",
    "push-wall-v3",
    "push-back-v3",
    "reach-v3",
    "reach-wall-v3",
    "shelf-place-v3",
    "sweep-into-v3",
    "sweep-v3",
    "window-open-v3",
    "window-close-v3",
)


@dataclass(frozen=True)
class MetaWorldTask:
    """One Meta-World task.

    Attributes:
        name: our full name, ``"metaworld/<env_name>"``.
        scene: always ``"metaworld"``.
        env_name: Meta-World's v3 environment name, e.g. ``"button-press-v3"``.
    """

    name: str
    scene: str
    env_name: str


TASKS: dict[str, MetaWorldTask] = {f"{SCENE}/{n}": MetaWorldTask(f"{SCENE}/{n}", SCENE, n) for n in ENV_NAMES}


def list_metaworld_tasks() -> list[str]:
    return list(TASKS)


def get_metaworld_task(name: str) -> MetaWorldTask:
    """The task called ``metaworld/<v3 name>``; a bare v3 name (``button-press-v3``) is accepted too."""
    key = name if name.startswith(f"{SCENE}/") else f"{SCENE}/{name}"
    try:
        return TASKS[key]
    except KeyError:
        raise ValueError(
            f"unknown Meta-World task {name!r}; names look like 'metaworld/button-press-v3' "
            f"(see studio.sim.metaworld_tasks.ENV_NAMES)"
        ) from None
