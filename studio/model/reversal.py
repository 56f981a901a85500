"""Time reversal of training pairs: a demonstration and its agent clips played backwards, as one new pair.

Reversing a demonstration *and* the agent trajectories paired with it gives a consistent pair of an "undo"
task: the demonstration now shows the window being opened, the drawer pulled out, the puck carried back, and
the agent's first frame (the old last frame) shows the scene where that motion starts; the agent's path, its
gripper commands and its future frames (the world model's targets) are read backwards too. Not in the paper.

Why: a training set can hold a scene with one motion only — Meta-World's 46 training tasks close the window
(push along −x) and never open it (the held-out window-open pushes along +x), so a policy may answer the scene
and ignore the demonstration. Reversed pairs show the same scene with the opposite motion, told apart only by
the demonstration. They start where the forward task ends (the arm at the object), not at the robot's rest pose.

One draw per demonstration: a demonstration and every pair of the batch that imitates it are reversed together,
so no pair mixes a forward demonstration with a reversed agent trajectory.
"""

from __future__ import annotations

from dataclasses import replace

import torch

from studio.model.batching import Batch


def reverse_pairs(batch: Batch, probability: float, g: torch.Generator) -> tuple[Batch, torch.Tensor]:
    """The batch with each demonstration (and its pairs) reversed in time with ``probability``.

    Returns the new batch and the (U,) bool mask of reversed demonstrations. The input batch is not changed.
    """
    u = batch.expert_frames.shape[0]
    chosen = torch.rand(u, generator=g) < probability
    if not bool(chosen.any()):
        return batch, chosen
    pairs = chosen.to(batch.expert_ids.device)[batch.expert_ids]
    expert = batch.expert_frames.clone()
    expert[chosen] = expert[chosen].flip(1)
    agent = batch.agent_frames.clone()
    agent[pairs] = agent[pairs].flip(1)
    path = batch.path.clone()
    path[pairs] = path[pairs].flip(1)
    return replace(batch, expert_frames=expert, agent_frames=agent, path=path), chosen
