"""The training recipes: named sequences of stages on top of the ``cpu`` preset, each stage's settings typed.

A :class:`Stage` is one ``studio train`` run: its default length, its seed (the recipe's seed plus an offset), the
``ModelConfig``/``TrainConfig`` values it sets over the preset, and the earlier stage whose checkpoint it starts
from. A :class:`Recipe` names the scene and its stages in order. ``studio train --recipe NAME --stage STAGE``
trains one stage (:func:`stage_config`); ``studio quickstart`` runs the pick-and-place recipes end to end.

* ``pick-place`` — the shipped ``pick-place-cpu`` (72×96): ``base`` without the world
  model, expert videos and pairs mirrored half the time; ``refine`` from ``base``'s last checkpoint with no
  warm-ups; ``grow`` adds 𝒲, untrained, to ``refine``'s best checkpoint with the encoder held fixed.
* ``pick-place-no-world-model`` — the paper's no-world-model ablation: ``pick-place`` without its ``grow`` stage.
* ``pick-place-quick`` — what ``studio quickstart`` trains: ``pick-place``'s stages at 48×64 input, 1300 + 900
  steps without 𝒲 and 600 with it.
* ``push`` — the shipped ``push-cpu``: ``base`` without the world model, then ``grow`` with the encoder fixed.
* ``metaworld`` — the shipped ``metaworld-cpu`` at 96×96, on the recorded gripper commands: ``base`` without the
  world model; ``grow`` with the encoder and π fixed; ``guide`` with the encoder fixed and demonstration dropout,
  so that the policy can be planned with guidance (``studio export-policy --guidance``); ``end`` continues
  ``guide`` with a loss on each plan's end (``train.endpoint_weight``) and crop, shift and zoom augmentation
  (the only Meta-World stage that augments); the policy is ``end`` exported with
  ``guide`` as its guided branch (``studio export-policy --guided-from``). The shipped file's ``guide`` and ``end``
  stages started from the float16 exports of the stage before; the recipe starts them from the checkpoints.

Why each setting is what it is: docs/experiments.md. The shipped policies' JSON files list the commands they
were trained with; each recipe is those commands (tests/model/test_recipes.py holds them to it).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import Any

from studio.model.config import RunConfig, preset


def _frozen(values: dict[str, Any]) -> MappingProxyType[str, Any]:
    return MappingProxyType(dict(values))


@dataclass(frozen=True)
class Stage:
    """One training run of a recipe.

    Attributes:
        name: how ``--stage`` names it.
        steps: its default number of optimiser steps.
        seed_offset: its seed is the recipe's seed plus this.
        model, train: ``ModelConfig`` and ``TrainConfig`` field values it sets over the preset (typed).
        init_from: the earlier stage whose checkpoint it starts from (None: random weights).
        init_checkpoint: which checkpoint of that stage: ``best`` (lowest validation loss; ``last`` when the
            stage has no validation) or ``last``.
    """

    name: str
    steps: int
    seed_offset: int = 0
    model: MappingProxyType[str, Any] = field(default_factory=lambda: _frozen({}))
    train: MappingProxyType[str, Any] = field(default_factory=lambda: _frozen({}))
    init_from: str | None = None
    init_checkpoint: str = "best"


@dataclass(frozen=True)
class Recipe:
    """A named sequence of stages for one scene, on top of a preset."""

    name: str
    scene: str
    stages: tuple[Stage, ...]
    preset: str = "cpu"

    def stage(self, name: str | None = None) -> Stage:
        """The stage called ``name`` (None: the first); ``ValueError`` naming the stages there are."""
        if name is None:
            return self.stages[0]
        for stage in self.stages:
            if stage.name == name:
                return stage
        raise ValueError(
            f"recipe {self.name!r} has no stage {name!r}; its stages: {', '.join(s.name for s in self.stages)}"
        )


_NO_WORLD_MODEL = {"world_model": False}
# Pick-and-place: tasks are named by colour, so a mirrored expert video still demonstrates its task ("grasp
# where the demonstration grasped" stops paying); pairs mirrored whole show the bar placed on the right too.
_PICK_PLACE_MIRRORS = {"expert_hflip": 0.5, "hflip": 0.5}
_PICK_PLACE_BASE = Stage("base", 1600, 0, _frozen(_NO_WORLD_MODEL), _frozen(_PICK_PLACE_MIRRORS))
_PICK_PLACE_REFINE = Stage(
    "refine",
    1100,
    1,
    _frozen(_NO_WORLD_MODEL),
    _frozen({**_PICK_PLACE_MIRRORS, "aug_warmup": 0.0, "alpha_warmup": 0.0}),
    init_from="base",
    init_checkpoint="last",
)
# 𝒲 starts untrained, so the preset's α warm-up stays; the encoder the earlier stages trained stays fixed.
_PICK_PLACE_GROW = Stage(
    "grow",
    700,
    2,
    train=_frozen({**_PICK_PLACE_MIRRORS, "aug_warmup": 0.0, "freeze": ("encoder",)}),
    init_from="refine",
)
# What ``studio quickstart`` trains: ``pick-place`` at 48×64 (a 6×8 grid) on a shorter schedule. Half the pixels
# halve a step (bf16, 2 threads: no-𝒲 0.40 → 0.20 s, grow 0.72 → 0.35 s on a synthetic batch); the bar and the
# zones stay several cells wide.
_QUICK_SIZE = {"image_size": (48, 64)}
_QUICK = tuple(
    replace(stage, steps=steps, model=_frozen({**stage.model, **_QUICK_SIZE}))
    for stage, steps in zip(
        (_PICK_PLACE_BASE, _PICK_PLACE_REFINE, _PICK_PLACE_GROW), (1300, 900, 600), strict=True
    )
)
_METAWORLD_SIZE = {"image_size": (96, 96)}
# The shipped Meta-World policy learnt the recorded gripper commands (0.5 for experts that never grasp), which
# make its button presses run the grasp branch's centring; binary labels, as the paper's, did worse (experiments.md).
_RECORDED = {"gripper_labels": "recorded"}
# The stages that train with demonstration dropout, the encoder fixed.
_METAWORLD_GUIDE = {
    "val_every": 250,
    "aug_warmup": 0.0,
    "freeze": ("encoder",),
    "demo_dropout": 0.2,
    **_RECORDED,
}

# The end stage's augmentation: the paper's random crop and translation, up to 5 % of the image (the reference
# code's 12 of 224 pixels), and a zoom of 0.95-1.05 (not in the paper); the labels stay in the camera frame
# (``augment``). No flips (they cost pick-place-wall) and no colour jitter (it cost every task; docs/experiments.md).
_METAWORLD_END_AUGMENTATION = {"crop": 0.05, "translate": 0.05, "scale": (0.95, 1.05)}

RECIPES: dict[str, Recipe] = {
    r.name: r
    for r in (
        Recipe("pick-place", "pick_place", (_PICK_PLACE_BASE, _PICK_PLACE_REFINE, _PICK_PLACE_GROW)),
        Recipe("pick-place-no-world-model", "pick_place", (_PICK_PLACE_BASE, _PICK_PLACE_REFINE)),
        Recipe("pick-place-quick", "pick_place", _QUICK),
        Recipe(
            "push",
            "push",
            (
                Stage("base", 1000, 0, _frozen(_NO_WORLD_MODEL), _frozen({"val_every": 200})),
                Stage(
                    "grow",
                    700,
                    2,
                    train=_frozen({"val_every": 200, "freeze": ("encoder",), "aug_warmup": 0.0}),
                    init_from="base",
                ),
            ),
        ),
        Recipe(
            "metaworld",
            "metaworld",
            (
                Stage(
                    "base",
                    2200,
                    0,
                    _frozen({**_METAWORLD_SIZE, **_NO_WORLD_MODEL}),
                    _frozen({"val_every": 550, **_RECORDED}),
                ),
                Stage(
                    "grow",
                    500,
                    2,
                    _frozen(_METAWORLD_SIZE),
                    _frozen(
                        {
                            "val_every": 250,
                            "aug_warmup": 0.0,
                            "freeze": ("encoder", "action_model"),
                            **_RECORDED,
                        }
                    ),
                    init_from="base",
                ),
                Stage(
                    "guide",
                    750,
                    4,
                    _frozen(_METAWORLD_SIZE),
                    _frozen({**_METAWORLD_GUIDE, "lr_max": 3e-4}),
                    init_from="grow",
                ),
                Stage(
                    "end",
                    500,
                    8,
                    _frozen(_METAWORLD_SIZE),
                    # the guide stage's settings at half its learning rate, with the loss on each plan's end and
                    # the pixel-space augmentation (crop, shift, zoom) that moves the ends onto the scene's objects
                    _frozen(
                        {
                            **_METAWORLD_GUIDE,
                            "lr_max": 1.5e-4,
                            "endpoint_weight": 60.0,
                            "precision": "bf16",
                            **_METAWORLD_END_AUGMENTATION,
                        }
                    ),
                    init_from="guide",
                ),
            ),
        ),
    )
}


def recipe(name: str) -> Recipe:
    """The recipe called ``name``; ``ValueError`` naming the recipes there are."""
    if name not in RECIPES:
        raise ValueError(f"unknown recipe {name!r}; choose from {', '.join(RECIPES)}")
    return RECIPES[name]


def stage_config(recipe_name: str, stage_name: str | None = None) -> tuple[RunConfig, Stage]:
    """The configuration of one stage of a recipe (the recipe's preset for its scene with the stage's values),
    and the stage. Raises ``ValueError`` for an unknown recipe or stage."""
    chosen = recipe(recipe_name)
    stage = chosen.stage(stage_name)
    run = preset(chosen.preset, chosen.scene).with_changes(model=dict(stage.model), train=dict(stage.train))
    return run, stage
