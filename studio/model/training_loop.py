"""The optimisation loop both trainers share: resume, step seeds, metrics, validation, best/last checkpoints,
cancellation and progress.

A trainer (:mod:`studio.model.train` for OSVI-WM, :mod:`studio.model.train_decoder` for the latent decoder)
builds its model, optimiser and schedule and gives a :class:`TrainingLoop` what differs between them: how to
restore a checkpoint, how to take one optimiser step, how to validate and what its checkpoints hold. The loop
owns the run directory's bookkeeping:

* ``last.pt`` — written atomically every ``checkpoint_every`` steps, on cancellation and at the end;
  ``best.pt`` — written when validation lowers ``best_metric``. Both hold the trainer's state plus ``step`` and the best
  value so far (under ``best_key``); :meth:`TrainingLoop.resume` continues from ``last.pt``.
* ``metrics.jsonl`` — trimmed on resume to the steps the checkpoint holds (a killed run's later records go);
  a training record every ``log_every`` steps (the step parts averaged over the window, ``lr``, optionally
  ``epoch`` and ``samples_per_s``), a validation record ``{"step", "split": "val", ...}`` every ``val_every``
  steps and at the end, and with ``log_events`` the start / resume / end events (an ``end`` with status
  ``failed`` and the error when a step raised).
* seeding — step τ's randomness must derive from ``step_seed(seed, τ, rank)``, which the loop hands to the
  step function, so a run resumed from ``last.pt`` retraces an uninterrupted one.
* after every step: validation (when due), ``progress`` (a dict: step, total_steps, [epoch], loss, lr,
  [samples_per_s], eta_s), then ``cancel`` is polled, then ``last.pt`` is written when due or cancelled. A
  caller watching files relies on this order: ``best.pt`` of a step exists when its progress is reported,
  its ``last.pt`` only after.

Under data parallelism (``world`` > 1) only rank 0 writes files, validates and reports progress; the ranks
meet after each validation and agree on cancellation.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar, cast

import numpy as np
import torch
import torch.distributed as dist
from torch.utils.data import DataLoader, Dataset

from studio.model.batching import BatchPlan, PairSource
from studio.model.run_files import append_jsonl, atomic_save, is_cancelled, step_seed, trim_metrics

LAST = "last.pt"
BEST = "best.pt"
METRICS = "metrics.jsonl"

B = TypeVar("B")


@dataclass
class TrainResult:
    """How a training run ended."""

    status: str  # "finished" or "cancelled"
    step: int
    total_steps: int
    out_dir: Path
    best_val_loss: float | None
    last_record: dict[str, Any]


@dataclass
class StepOutput:
    """What one optimiser step reports: its parts (averaged into the metrics records) and the learning rate
    it used."""

    parts: dict[str, float]
    lr: float


def cosine_schedule(
    optimizer: torch.optim.Optimizer, total: int, warmup: int = 0
) -> torch.optim.lr_scheduler.LambdaLR:
    """Linear warm-up over ``warmup`` steps, then a cosine decay to 1/100 of the optimiser's rate at ``total``:
    the schedule of the decoder and encoder trainers."""

    def factor(step: int) -> float:
        ramp = min(1.0, (step + 1) / warmup) if warmup > 0 else 1.0
        return ramp * (0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * min(step / max(total - 1, 1), 1.0))))

    return torch.optim.lr_scheduler.LambdaLR(optimizer, factor)


def _seed_worker(worker_id: int) -> None:
    """Seed numpy in each DataLoader worker from torch's seed (itself derived from the step seed)."""
    np.random.seed(torch.initial_seed() % (2**32))  # noqa: NPY002 - datasets may use numpy's global RNG


def plan_batches(
    dataset: PairSource,
    plan: BatchPlan,
    total: int,
    collate: Callable[[list[Any]], B],
    num_workers: int,
    *,
    world: int = 1,
    rank: int = 0,
) -> Callable[[int], Iterator[tuple[int, B]]]:
    """The batches of ``plan`` from a given step to ``total``, as ``(step, batch)``: epoch after epoch, one
    DataLoader per epoch (``dataset.set_epoch(epoch)`` first when it has one), each rank taking its contiguous
    slice of every global batch. Starting at any step gives the batches an uninterrupted run had there."""
    per_rank = plan.batch_size // world
    per_epoch = plan.batches_per_epoch

    def batches_from(step: int) -> Iterator[tuple[int, B]]:
        while step < total:
            epoch, offset = divmod(step, per_epoch)
            chunks = [b[rank * per_rank : (rank + 1) * per_rank] for b in plan.epoch(epoch)[offset:]]
            chunks = chunks[: total - step]
            if hasattr(dataset, "set_epoch"):
                dataset.set_epoch(epoch)
            loader = DataLoader(
                cast(Dataset, dataset),  # any map-style source: the loader only indexes it and takes its len
                batch_sampler=chunks,
                collate_fn=collate,
                num_workers=num_workers,
                worker_init_fn=_seed_worker,
            )
            for batch in loader:
                yield step, batch
                step += 1

    return batches_from


@dataclass
class TrainingLoop:
    """The steps of one run from ``start_step`` to ``total``, with the bookkeeping of the module docstring.

    Attributes:
        out: the run directory (the caller creates it).
        total: the step the run ends at.
        seed: the run's seed; step τ gets ``step_seed(seed, τ, rank)``.
        log_every, val_every, checkpoint_every: cadences in steps (the last step always logs, validates and
            checkpoints).
        best_metric: the validation value whose minimum selects ``best.pt``.
        best_key: the checkpoint key holding the best value so far.
        loss_key: the step part reported as ``loss`` in progress and on the progress bar.
        name: the progress bar's label.
        epoch_length: batches per epoch; when given, records and progress carry ``epoch``.
        samples_per_step: samples per step over all ranks; when given, records and progress carry
            ``samples_per_s``.
        log_events: also log start / resume / end events in ``metrics.jsonl``.
        world, rank: data-parallel processes and this one's rank.
        start_step, best: where the run stands (0 and None until :meth:`resume` finds a checkpoint).
    """

    out: Path
    total: int
    seed: int
    log_every: int
    val_every: int
    checkpoint_every: int
    best_metric: str
    best_key: str
    loss_key: str = "loss"
    name: str = "train"
    epoch_length: int | None = None
    samples_per_step: int | None = None
    log_events: bool = False
    world: int = 1
    rank: int = 0
    start_step: int = 0
    best: float | None = None

    @property
    def main(self) -> bool:
        """Whether this process writes the files (rank 0)."""
        return self.rank == 0

    @property
    def last_path(self) -> Path:
        return self.out / LAST

    @property
    def metrics_path(self) -> Path:
        return self.out / METRICS

    def resume(
        self, read: Callable[[Path], dict[str, Any]], restore: Callable[[dict[str, Any]], None]
    ) -> bool:
        """Continue from ``last.pt`` when there is one; False otherwise.

        ``read`` loads the checkpoint, ``restore`` checks that it belongs to this run (raising otherwise) and
        loads the trainer's state from it; the loop takes the step reached and the best value so far.
        """
        if not self.last_path.exists():
            return False
        ckpt = read(self.last_path)
        restore(ckpt)
        self.start_step, self.best = int(ckpt["step"]), ckpt.get(self.best_key)
        return True

    def run(
        self,
        batches: Callable[[int], Iterator[tuple[int, B]]],
        step: Callable[[int, B, int], StepOutput],
        state: Callable[[], dict[str, Any]],
        *,
        validate: Callable[[int], dict[str, float]] | None = None,
        progress: Callable[[dict[str, Any]], None] | None = None,
        cancel: Any = None,
        show_progress: bool = True,
    ) -> TrainResult:
        """Train from ``start_step`` to ``total`` or until cancelled.

        ``batches(start)`` yields ``(step, batch)`` from ``start`` on; ``step(τ, batch, seed)`` takes one
        optimiser step and must draw its randomness from ``seed``; ``state()`` is the trainer's part of a
        checkpoint; ``validate(τ)`` (rank 0 only) returns the validation values after step τ, including
        ``best_metric``; ``cancel`` is a callable returning bool or anything with ``is_set()``.
        """
        total, main, world = self.total, self.main, self.world

        def save(step: int, name: str) -> None:
            if main:
                atomic_save({**state(), "step": step, self.best_key: self.best}, self.out / name)

        if main:
            trim_metrics(self.metrics_path, self.start_step)
            if self.log_events:
                self._event(
                    "resume" if self.start_step else "start",
                    step=self.start_step,
                    total_steps=total,
                    world_size=world,
                )
        bar = None
        if show_progress and main:
            from tqdm import tqdm

            bar = tqdm(
                total=total,
                initial=self.start_step,
                desc=self.name,
                unit="step",
                file=sys.stderr,
                dynamic_ncols=True,
            )
        status, done, record = "finished", self.start_step, {}
        sums: dict[str, float] = {}
        window_start, window_steps = time.perf_counter(), 0
        run_start = time.perf_counter()
        try:
            for index, batch in batches(self.start_step):
                out = step(index, batch, step_seed(self.seed, index, self.rank))
                done = index + 1
                window_steps += 1
                for k, v in out.parts.items():
                    sums[k] = sums.get(k, 0.0) + v
                if done % self.log_every == 0 or done == total:
                    record = {"step": done, **self._epoch(done, 4), "lr": out.lr}
                    if self.samples_per_step is not None:
                        elapsed = time.perf_counter() - window_start
                        record["samples_per_s"] = window_steps * self.samples_per_step / max(elapsed, 1e-9)
                    record.update({k: v / window_steps for k, v in sums.items()})
                    if main:
                        append_jsonl(self.metrics_path, record)
                    window_start, window_steps, sums = time.perf_counter(), 0, {}
                if validate is not None and (done % self.val_every == 0 or done == total):
                    if main:
                        val = validate(done)
                        append_jsonl(self.metrics_path, {"step": done, "split": "val", **val})
                        if self.best is None or val[self.best_metric] < self.best:
                            self.best = val[self.best_metric]
                            save(done, BEST)
                    if world > 1:
                        dist.barrier()
                loss = out.parts[self.loss_key]
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix({self.loss_key: f"{loss:.4f}", "lr": f"{out.lr:.2e}"})
                if progress is not None and main:
                    rate = (done - self.start_step) / max(time.perf_counter() - run_start, 1e-9)
                    info: dict[str, Any] = {"step": done, "total_steps": total, **self._epoch(done)}
                    info.update(loss=loss, lr=out.lr)
                    if self.samples_per_step is not None:
                        info["samples_per_s"] = rate * self.samples_per_step
                    info["eta_s"] = (total - done) / max(rate, 1e-9)
                    progress(info)
                stop = is_cancelled(cancel)
                if world > 1:
                    flag = torch.tensor([1.0 if stop else 0.0])
                    dist.all_reduce(flag)
                    stop = bool(flag.item() > 0)
                if done % self.checkpoint_every == 0 or done == total or stop:
                    save(done, LAST)
                if stop:
                    status = "cancelled"
                    break
        except Exception as exc:
            if main and self.log_events:  # said in the run's own record, not only by whoever ran it
                self._event("end", status="failed", step=done, error=str(exc)[:500] or type(exc).__name__)
            raise
        finally:
            if bar is not None:
                bar.close()
        if main and self.log_events:
            self._event("end", status=status, step=done)
        return TrainResult(status, done, total, self.out, self.best, record)

    def _epoch(self, step: int, digits: int | None = None) -> dict[str, float]:
        if self.epoch_length is None:
            return {}
        epoch = step / self.epoch_length
        return {"epoch": epoch if digits is None else round(epoch, digits)}

    def _event(self, event: str, **fields: Any) -> None:
        append_jsonl(self.metrics_path, {"event": event, **fields, "time": time.time()})
