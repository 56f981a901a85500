"""OSVI Studio: one-shot visual imitation with OSVI-WM, from recording to rollout inspection."""

__version__ = "0.1.0"
