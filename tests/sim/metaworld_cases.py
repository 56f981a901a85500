"""Meta-World tasks the simulator tests exercise: the paper's four test tasks, each beside the training task it
looks most like (same objects, different goal), so that a mix-up between the two shows."""

TEST_AND_TWINS = [
    "metaworld/button-press-v3",
    "metaworld/button-press-wall-v3",
    "metaworld/pick-place-wall-v3",
    "metaworld/pick-place-v3",
    "metaworld/window-open-v3",
    "metaworld/window-close-v3",
    "metaworld/door-unlock-v3",
    "metaworld/door-lock-v3",
]
