"""Demonstration guidance: training with the demonstration sometimes withheld, planning with its effect scaled.

Not in the paper. It carries classifier-free guidance (Ho & Salimans, 2022) over to one-shot imitation. During
training, ``TrainConfig.demo_dropout`` replaces each demonstration (with every pair that imitates it) by the
*null demonstration* — all-black frames — with that probability, so the same network also learns to plan from
the scene alone. At planning, ``ModelConfig.guidance`` = g plans twice, with the demonstration and with the null
one, and combines the raw waypoint rows (x, y, depth, gripper logit) as

    rows = null + g · (demonstration − null).

g = 1 is the demonstration alone (the paper; no second plan); g > 1 moves the plan further the way the
demonstration moves it away from what the scene alone suggests.

The gate (``ModelConfig.guidance_gate``): guidance helps where the demonstration shows a motion its scene does not
suggest, and harms where the scene alone already explains it (the extrapolation then only adds error). The world
model says which: ``demonstration_gain`` replays the demonstration's own first frame through π and 𝒲, once with
the demonstration and once with the null one, and compares both predicted latent trajectories with the
demonstration's real later frames. The gain is the null prediction's error over the demonstration's; about 1
when the scene alone predicts what the demonstrator did, larger when it does not. A gated policy guides only
demonstrations whose gain reaches the gate; the gain depends on the demonstration alone, so it is computed once
per demonstration, not per plan.

Why: where the training set shows a scene with one motion only (Meta-World closes the window and never opens
it), the planner learns to answer the scene, and the demonstration's part in the plan stays small. Guidance
amplifies that part at planning time without changing the scenes the model was trained on. A model trained
without ``demo_dropout`` has never seen the null demonstration, so guidance is meaningful only for models
trained with it.

The guided branch (``studio export-policy --guided-from``): a policy file may carry a second set of weights for
π, 𝒲 and the head, on the same encoder, which computes the gain and plans the demonstrations that reach the gate;
the policy's own weights plan the others, from the demonstration alone. A later fine-tune can then make the plans
that need no guidance more precise without touching the guided ones: on Meta-World a loss on each plan's end
lifted the easy tasks and cost the guided door-unlock plans, and the policy shipped with both branches keeps each
(docs/experiments.md).

The gain's scale is the run's: ``studio export-policy --gate-percentile`` sets the gate from the run's own training
demonstrations (the shipped Meta-World policy is gated at their 95th percentile).

The surprise gate (``ModelConfig.surprise_gate``): the gain misses a demonstration that the world model predicts
badly with it and without it alike — its reading of the demonstration is itself wrong, so the demonstration barely
moves the prediction. On Meta-World window-open is such a task: its first frames look like window-close's, the one
window task in training, so the plan closes the window with or without the demonstration (gain about 1), and the
prediction of the demonstration's later frames misses by more than for nearly every training demonstration.
``demonstration_surprise`` is that error (the gain's denominator); a policy with a surprise gate also guides, with
its own weights, the demonstrations whose surprise reaches it. ``studio export-policy --surprise-percentile`` reads
it off the training demonstrations' surprises, as ``--gate-percentile`` does the gate. Its plans come from other
weights than the gate's (the policy's own, not the branch's), which extrapolate best at another scale:
``ModelConfig.surprise_guidance`` (``--surprise-guidance``) sets theirs. Off by default (g = 1, no gate).
What guidance and the gate do on Meta-World, task by task, is measured in docs/experiments.md ("How far is
Meta-World from the paper, and what moved it?"); the shipped policy's figures are in docs/results.md.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from studio.model.osvi_wm import OSVIWM
    from studio.model.transformer import KVCache


def null_demonstration(like: torch.Tensor) -> torch.Tensor:
    """The null demonstration: black frames of ``like``'s shape, dtype and device."""
    return torch.zeros_like(like)


def drop_demonstrations(
    expert_frames: torch.Tensor, probability: float, g: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """Replace each demonstration of (U, N, 3, H, W) ``expert_frames`` by the null one with ``probability``.

    One draw per demonstration; the pairs that imitate it see the null demonstration through their
    ``expert_ids``. Returns the frames (the input is not changed) and the (U,) bool mask of dropped ones.
    """
    chosen = torch.rand(expert_frames.shape[0], generator=g) < probability
    if not bool(chosen.any()):
        return expert_frames, chosen
    out = expert_frames.clone()
    rows = chosen.to(out.device)
    out[rows] = null_demonstration(out[rows])
    return out, chosen


def guide(with_demo: torch.Tensor, without_demo: torch.Tensor, scale: float) -> torch.Tensor:
    """``without_demo + scale · (with_demo − without_demo)``: the raw rows planned with guidance ``scale``."""
    return without_demo + scale * (with_demo - without_demo)


def prediction_error(model: OSVIWM, expert_states: torch.Tensor, context: KVCache) -> float:
    """How far π and 𝒲 predict the demonstration's own video from its first frame, through π's cache ``context``.

    ``expert_states`` (N, *state_shape) are the encoded demonstration frames. The recursion from the first frame
    predicts the later states; each is compared (pooled keypoints, L2) with the demonstration's frame at the same
    fraction of the video as the training targets' agent frames, and the distances are summed.
    """
    if model.world_model is None:
        raise ValueError(
            "the demonstration's prediction error needs the world model (ModelConfig.world_model)"
        )
    n, m = expert_states.shape[0], model.cfg.n_agent_frames
    targets = [round(i / (m - 1) * (n - 1)) for i in model.target_frame_indices()]
    actual = model.pool(expert_states[targets])
    _, states = model.rollout_from_context(context, expert_states[:1])
    return float((model.pool(states)[0] - actual).norm(dim=-1).sum())


def demonstration_gain(
    model: OSVIWM, expert_states: torch.Tensor, context: KVCache, null_context: KVCache
) -> float:
    """How much better the world model predicts the demonstration's own video with it than from its scene alone.

    ``context`` and ``null_context`` are π's caches of the demonstration and of the null one; returns
    ``prediction_error`` through the null context over that through the demonstration's.
    """
    return prediction_error(model, expert_states, null_context) / max(
        prediction_error(model, expert_states, context), 1e-12
    )


def demonstration_surprise(model: OSVIWM, expert_states: torch.Tensor, context: KVCache) -> float:
    """How badly the world model predicts the demonstration's own video even with it: ``prediction_error`` through
    the demonstration's context (the gain's denominator)."""
    return prediction_error(model, expert_states, context)
