"""What the demonstration-task loss names, and the loss (``TrainConfig.demo_task_weight``; not in the paper).

π's outputs at the expert frames, averaged, go through a small classifier (``OSVIWM.demo_task_head``) that is
trained to name what the demonstration shows. ``TrainConfig.demo_task_labels`` chooses the names:

* ``"task"`` — one class per training task. On unseen tasks π then answers with the nearest training task:
  push's held-out ``blue-backward`` was pushed forward like ``blue-forward`` (docs/experiments.md).
* ``"parts"`` — one classifier per part of a tabletop task: the object (pick-and-place) or box (push), and the
  target zone or push direction. Every part of a held-out combination (``bar`` and ``yellow`` in
  ``bar->yellow``) was named in training, so its name is made of names π has learned; the whole-task labels
  give it none. Meta-World tasks have no such parts. The parts are read from the task names
  (``pick_place/<object>-><target>``, ``push/<box>-<forward|backward>``, the names of ``studio.sim.tasks``), so
  the model never needs the simulator's task registry.

The classifier's logits are the groups' logits side by side (``ModelConfig.demo_task_groups``; one group of
``demo_task_classes`` when empty), and ``ModelConfig.demo_task_table`` maps a training-task index to its class in
each group (the identity when empty). Both live in the model's configuration, so a checkpoint says what its head
names.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch
import torch.nn.functional as F

LABELLINGS = ("task", "parts")
PUSH_DIRECTIONS = ("forward", "backward")


class TaskParts(NamedTuple):
    """What a tabletop task is about: the object (or box) and the target zone (or push direction)."""

    obj: str
    target: str


def label_table(tasks: Sequence[str], labels: str) -> tuple[tuple[int, ...], tuple[tuple[int, ...], ...]]:
    """``(groups, table)`` for the training ``tasks`` under a labelling: the size of each group and, per task,
    its class in each group (``table`` is empty for ``"task"``: task *i* is class *i*)."""
    if labels == "task":
        return (len(tasks),), ()
    if labels != "parts":
        raise ValueError(
            f"unknown demonstration-task labelling {labels!r}; choose from {', '.join(LABELLINGS)}"
        )
    found = [_task(name) for name in tasks]
    objects, targets = _parts(found)
    return (len(objects), len(targets)), tuple((objects.index(t.obj), targets.index(t.target)) for t in found)


def class_names(tasks: Sequence[str], table: Sequence[Sequence[int]]) -> list[list[str]]:
    """Readable names of each group's classes: the training tasks' short names (``"cube->red"``) for whole-task
    labels, the objects and the targets for parts (what ``label_table`` numbered)."""
    if not table:
        return [[name.partition("/")[2] or name for name in tasks]]
    return list(_parts([_task(name) for name in tasks]))


def task_parts(name: str) -> TaskParts | None:
    """The object and target a tabletop task name is made of, or None for a name of another form."""
    scene, _, what = name.partition("/")
    if scene == "pick_place":
        obj, sep, target = what.partition("->")
    elif scene == "push":
        obj, sep, target = what.rpartition("-")
        sep = sep if target in PUSH_DIRECTIONS else ""
    else:
        return None
    return TaskParts(obj, target) if sep and obj and target else None


def _task(name: str) -> TaskParts:
    parts = task_parts(name)
    if parts is None:
        raise ValueError(
            f"demonstration-task labels 'parts' need tasks made of an object and a target; {name} is not "
            "(use train.demo_task_labels=task)"
        )
    return parts


def _parts(found: Sequence[TaskParts]) -> tuple[list[str], list[str]]:
    """The objects and the targets of the training tasks, in order of first appearance (the classes' order)."""
    objects = list(dict.fromkeys(t.obj for t in found))
    targets = list(dict.fromkeys(t.target for t in found))
    for kind, names in (("object", objects), ("target", targets)):
        if len(names) < 2:
            raise ValueError(
                f"demonstration-task labels 'parts': the training tasks have one {kind} only ({names[0]})"
            )
    return objects, targets


def demo_task_loss(
    logits: torch.Tensor, expert_tasks: torch.Tensor, groups: Sequence[int], table: Sequence[Sequence[int]]
) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean cross-entropy over the groups, and per demonstration whether every group was named right.

    Args:
        logits: (U, sum(groups)) the head's output per expert video.
        expert_tasks: (U,) training-task index of each expert video.
        groups, table: ``ModelConfig.demo_task_groups`` / ``demo_task_table`` (see the module docstring).
    """
    if not groups:
        groups = (logits.shape[-1],)
    if sum(groups) != logits.shape[-1]:
        raise ValueError(
            f"the head gives {logits.shape[-1]} logits, the groups {tuple(groups)} need {sum(groups)}"
        )
    if table:
        labels = torch.as_tensor(table, dtype=torch.long, device=logits.device)[
            expert_tasks.to(logits.device)
        ]
    else:
        labels = expert_tasks.to(logits.device).long()[:, None]
    losses, right = [], torch.ones(logits.shape[0], dtype=torch.bool, device=logits.device)
    for g, part in enumerate(logits.float().split(list(groups), dim=-1)):
        losses.append(F.cross_entropy(part, labels[:, g]))
        right &= part.argmax(-1) == labels[:, g]
    return torch.stack(losses).mean(), right
