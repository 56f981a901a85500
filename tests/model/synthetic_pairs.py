"""The synthetic task of the model tests (it lives in ``studio.bench.synthetic_task``, shared with the benchmark)."""

from studio.bench.synthetic_task import TARGET_COLOURS, TARGETS_CAM, SyntheticPairs, tiny_run_config

__all__ = ["TARGETS_CAM", "TARGET_COLOURS", "SyntheticPairs", "tiny_run_config"]
