"""The smallest OSVI-WM the tests train: ``--set`` overrides that keep a training run to seconds on one thread.

``TINY`` is the network and bookkeeping; ``TINY_BATCHED`` adds a batch of four pairs, two per demonstration.
"""

TINY = [
    "model.image_size=[48, 64]",
    "model.n_expert_frames=4",
    "model.n_agent_frames=3",
    "model.encoder_stages=2",
    "model.state_channels=16",
    "model.action_blocks=1",
    "model.action_heads=2",
    "model.action_attn_dim=16",
    "model.action_mlp_dim=32",
    "model.wm_blocks=1",
    "model.wm_heads=2",
    "model.wm_width=32",
    "model.wm_mlp_dim=64",
    "model.head_hidden=64",
    "train.num_workers=0",
    "train.log_every=1",
    "train.checkpoint_every=2",
    "train.val_every=1000",
]
TINY_BATCHED = [*TINY, "train.batch_size=4", "train.pairs_per_expert=2"]
