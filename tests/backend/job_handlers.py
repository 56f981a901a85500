"""Job handlers used by the backend tests: real work (counting, checkpoint files), small and deterministic.

Workers load them with ``--handler count=job_handlers:count_steps`` (tests put this directory on
``PYTHONPATH``).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from studio.backend.job_runner import JobContext


def count_steps(ctx: JobContext) -> dict:
    """Count to ``spec["steps"]``, one step per ``spec["step_s"]`` seconds, checkpointing to
    ``spec["run_dir"]/checkpoint.json`` every ``spec["every"]`` steps and resuming from it.

    ``spec["fail_at"]`` makes the handler raise at that step (to test failure reporting).
    """
    spec = ctx.spec
    total = int(spec["steps"])
    every = int(spec.get("every", 1))
    run_dir = Path(spec["run_dir"])
    run_dir.mkdir(parents=True, exist_ok=True)
    ckpt = run_dir / "checkpoint.json"
    start = json.loads(ckpt.read_text())["step"] if ckpt.exists() else 0
    with open(run_dir / "attempts.log", "a") as log:
        log.write(f"{ctx.attempt} {ctx.worker} {start}\n")
    for step in range(start, total):
        if ctx.wait_cancelled(float(spec.get("step_s", 0.01))):
            ctx.raise_if_cancelled()
        if spec.get("fail_at") is not None and step == int(spec["fail_at"]):
            raise RuntimeError(f"asked to fail at step {step}")
        done = step + 1
        if done % every == 0 or done == total:
            tmp = ckpt.with_suffix(".tmp")
            tmp.write_text(json.dumps({"step": done}))
            os.replace(tmp, ckpt)
            ctx.artifact("checkpoint", ckpt, step=done)
        ctx.progress(done, total, loss=1.0 / done)
    return {"counted": total, "resumed_from": start, "attempt": ctx.attempt, "worker": ctx.worker}
