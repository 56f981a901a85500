"""How far a demonstration is from the demonstrations a policy learnt from: a score, and its calibrated threshold.

A policy plans from whatever video it is given: a three-second video of a coloured blob is planned and executed
as if it showed a task. The *demonstration score* says how unlike the policy's training demonstrations a
demonstration looks to the policy's own encoder, so that the studio can warn before such a plan is trusted.

**Score.** Each of the demonstration's frames the planner looks at (``n_expert_frames``, evenly spaced, at the
model's input size) is encoded by the policy's encoder; a frame's feature is the mean and standard deviation over
the image of each encoder channel (a model that pools before the world model: its keypoints). Features are
standardised with the reference set's per-feature mean and spread, and each frame's distance to its nearest
reference frame is taken (root mean square over features). The score is the median of those distances over the
demonstration's frames: about 1 for a demonstration like the training ones, far above for one the encoder has
never seen anything like. The reference set is the frames of the policy's training demonstrations (its training
tasks, by the embodiments it learnt from).

**Calibration.** The threshold is set from two groups scored the same way: real *held-out* demonstrations —
scripted demonstrations of the scene's held-out tasks, never trained on, by the embodiments the policy learnt
from — which must pass, and meaningless videos made here (:func:`synthetic_videos`: a coloured blob drifting on a
plain background, as a phone might film one, uniform noise, a single flat colour, each at several colours and
seeds), which should not. The threshold is the geometric mean of the highest held-out score and the lowest
synthetic one when the two groups separate, else 1.1 × the highest held-out score (so that no held-out
demonstration seen is warned about; the calibration then records how many synthetic videos pass). A store without
held-out demonstrations calibrates on the training demonstrations themselves, each scored against the others
(leave one demonstration out), and says so.

A calibration is stored beside its checkpoint as ``<stem>.demo-score.npz`` (:func:`calibration_path`): the
shipped policies carry theirs (made by ``python -m studio.eval.demo_score``, which prints the figures); for any
other checkpoint the first plan computes it from the store's demonstrations and caches it there (a few seconds
for the studio's small models). Scoring a demonstration costs one encoding of its frames and a nearest-neighbour
search over a few hundred reference frames, a few milliseconds; it depends on the demonstration alone, so a
worker computes it once per (checkpoint, demonstration).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from studio.data.atomic_files import atomic_write

#: The calibration file beside a checkpoint ``<stem>.pt``.
SUFFIX = ".demo-score.npz"
#: Reference demonstrations per training task read from a store when calibrating (the first by id).
REFERENCE_PER_TASK = 12
#: Held-out demonstrations per held-out task read from a store when calibrating.
HELD_OUT_PER_TASK = 10
#: The file format, bumped when the score's definition changes (an older file is then recomputed).
FORMAT = 1
_STD_FLOOR = 1e-3


@dataclass(frozen=True)
class DemoScore:
    """A demonstration's score against a policy's calibration."""

    score: float
    threshold: float
    calibration: str  # how the threshold was set, in a few words

    @property
    def familiar(self) -> bool:
        return self.score <= self.threshold

    def to_dict(self) -> dict[str, Any]:
        return {
            "score": self.score,
            "threshold": self.threshold,
            "familiar": self.familiar,
            "calibration": self.calibration,
        }


@dataclass
class Calibration:
    """A policy's reference features and the threshold set from held-out and synthetic demonstrations."""

    mean: np.ndarray  # (D,) per-feature mean of the reference frames
    spread: np.ndarray  # (D,) per-feature standard deviation (floored)
    reference: np.ndarray  # (M, D) standardised reference frame features
    threshold: float
    positives: np.ndarray  # scores of the held-out demonstrations
    negatives: np.ndarray  # scores of the synthetic videos
    negative_kinds: list[str] = field(default_factory=list)
    source: str = ""  # what the positives were
    checkpoint_stamp: str = ""  # size and mtime of the checkpoint it belongs to

    def score_features(self, features: np.ndarray) -> float:
        """The score of a demonstration given its (n, D) frame features."""
        return float(np.median(nearest_distances((features - self.mean) / self.spread, self.reference)))

    def describe(self) -> str:
        """The calibration in one line: the held-out and synthetic scores and the threshold between them."""
        pos, neg = self.positives, self.negatives
        passed = int((neg <= self.threshold).sum())
        return (
            f"threshold {self.threshold:.2f}, set from {len(pos)} {self.source} (scores {pos.min():.2f}–"
            f"{pos.max():.2f}, median {np.median(pos):.2f}) and {len(neg)} synthetic videos (blob, noise, flat; "
            f"{neg.min():.2f}–{neg.max():.2f}, {passed} below the threshold)"
        )

    def figures(self) -> dict[str, Any]:
        pos, neg = self.positives, self.negatives
        kinds = sorted(set(self.negative_kinds))
        by_kind = {
            k: [float(s) for s, kk in zip(neg, self.negative_kinds, strict=True) if kk == k] for k in kinds
        }
        return {
            "threshold": self.threshold,
            "source": self.source,
            "held_out": len(pos),
            "held_out_min": float(pos.min()),
            "held_out_median": float(np.median(pos)),
            "held_out_max": float(pos.max()),
            "synthetic": len(neg),
            "synthetic_min": {k: min(v) for k, v in by_kind.items()},
            "synthetic_below_threshold": int((neg <= self.threshold).sum()),
            "reference_frames": len(self.reference),
        }

    def save(self, path: str | os.PathLike) -> None:
        arrays = dict(
            format=np.int64(FORMAT),
            mean=self.mean.astype(np.float32),
            spread=self.spread.astype(np.float32),
            reference=self.reference.astype(np.float16),
            threshold=np.float64(self.threshold),
            positives=self.positives.astype(np.float64),
            negatives=self.negatives.astype(np.float64),
            negative_kinds=np.asarray(self.negative_kinds, dtype=str),
            source=np.asarray(self.source),
            checkpoint_stamp=np.asarray(self.checkpoint_stamp),
        )
        atomic_write(path, lambda f: np.savez_compressed(f, allow_pickle=False, **arrays))

    @classmethod
    def load(cls, path: str | os.PathLike) -> Calibration:
        """Read a calibration file; ``ValueError`` when it is not one of the current format."""
        try:
            with np.load(path, allow_pickle=False) as d:
                if int(d["format"]) != FORMAT:
                    raise ValueError(f"{path} is a demonstration-score file of another format")
                return cls(
                    d["mean"].astype(np.float64),
                    d["spread"].astype(np.float64),
                    d["reference"].astype(np.float32),
                    float(d["threshold"]),
                    d["positives"],
                    d["negatives"],
                    [str(k) for k in d["negative_kinds"]],
                    str(d["source"]),
                    str(d["checkpoint_stamp"]),
                )
        except (KeyError, OSError, EOFError, ValueError) as e:  # numpy: ValueError for a file it cannot read
            if "another format" in str(e):
                raise
            raise ValueError(f"{path} is not a demonstration-score file: {e}") from None


def nearest_distances(features: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Each row's distance to its nearest reference row, root mean square over features."""
    f = np.asarray(features, np.float64)
    r = np.asarray(reference, np.float64)
    d2 = (f * f).sum(1)[:, None] - 2.0 * f @ r.T + (r * r).sum(1)[None, :]
    return np.sqrt(np.maximum(d2.min(1), 0.0) / f.shape[1])


def choose_threshold(positives: Sequence[float], negatives: Sequence[float]) -> float:
    """Between the held-out scores (which must pass) and the synthetic ones (see the module's docstring)."""
    pos, neg = np.asarray(positives, np.float64), np.asarray(negatives, np.float64)
    if len(pos) == 0:
        raise ValueError("calibrating needs at least one held-out demonstration")
    top = float(pos.max())
    if len(neg) and float(neg.min()) > top:
        return float(np.sqrt(top * float(neg.min())))
    return 1.1 * top


# ---------------------------------------------------------------------------------------------- features
def sampled(frames: np.ndarray, n: int) -> np.ndarray:
    """``n`` evenly spaced frames of a (T, H, W, 3) video, first and last kept (as the planner samples them)."""
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or len(frames) == 0:
        raise ValueError(f"a demonstration is (T, H, W, 3) frames, got shape {frames.shape}")
    return frames[np.round(np.linspace(0, len(frames) - 1, n)).astype(int)]


def frame_features(model, frames: np.ndarray) -> np.ndarray:
    """(n, D) features of a demonstration's sampled frames under ``model``'s encoder (see the module's docstring).

    ``model`` is an :class:`~studio.model.osvi_wm.OSVIWM` (a planner's, in eval mode); ``frames`` (T, H, W, 3)
    uint8 at any size.
    """
    import torch
    from torch.nn import functional as F

    cfg = model.cfg
    x = torch.as_tensor(np.ascontiguousarray(sampled(frames, int(cfg.n_expert_frames)))).permute(0, 3, 1, 2)
    size = (int(cfg.image_size[0]), int(cfg.image_size[1]))
    if tuple(x.shape[-2:]) != size:
        x = F.interpolate(x.float(), size=size, mode="bilinear", antialias=True, align_corners=False)
        x = x.round().clamp(0, 255).to(torch.uint8)
    device = next(model.parameters()).device
    with torch.inference_mode():
        states = model.encode(x.to(device)).float()
    if states.ndim == 4:  # (n, C, h, w) maps: each channel's mean and spread over the image
        feats = torch.cat([states.mean((-2, -1)), states.std((-2, -1))], dim=1)
    else:
        feats = states.reshape(len(states), -1)
    return feats.cpu().numpy().astype(np.float64)


def synthetic_videos(size: tuple[int, int], seed: int = 0) -> list[tuple[str, np.ndarray]]:
    """Meaningless videos of (H, W) frames: drifting coloured blobs, noise, flat colours (kind, (T, H, W, 3))."""
    rng = np.random.default_rng(seed)
    h, w = size
    out: list[tuple[str, np.ndarray]] = []
    yy, xx = np.mgrid[0:h, 0:w]
    for _ in range(8):
        background = rng.integers(0, 256, 3)
        colour = rng.integers(0, 256, 3)
        radius = rng.uniform(0.12, 0.3) * min(h, w)
        start, end = rng.uniform(0.2, 0.8, 2) * (h, w), rng.uniform(0.2, 0.8, 2) * (h, w)
        frames = np.empty((24, h, w, 3), np.uint8)
        for t in range(24):
            cy, cx = start + (end - start) * t / 23
            inside = (yy - cy) ** 2 + (xx - cx) ** 2 <= radius**2
            frames[t] = np.where(inside[..., None], colour, background)
        out.append(("blob", frames))
    for _ in range(3):
        out.append(("noise", rng.integers(0, 256, (24, h, w, 3), dtype=np.uint8)))
    for _ in range(3):
        out.append(("flat", np.broadcast_to(rng.integers(0, 256, 3).astype(np.uint8), (24, h, w, 3)).copy()))
    return out


# ---------------------------------------------------------------------------------------------- calibrating
def calibrate(
    model,
    reference: Sequence[np.ndarray],
    held_out: Sequence[np.ndarray],
    *,
    synthetic: Sequence[tuple[str, np.ndarray]] | None = None,
    checkpoint_stamp: str = "",
) -> Calibration:
    """A calibration from the policy's training demonstrations (``reference`` videos) and held-out ones.

    Without ``held_out`` videos each reference demonstration is scored against the others (leave one out).
    """
    if not reference:
        raise ValueError("calibrating needs the policy's training demonstrations (none given)")
    per_demo = [frame_features(model, v) for v in reference]
    stacked = np.concatenate(per_demo)
    mean, spread = stacked.mean(0), np.maximum(stacked.std(0), _STD_FLOOR)
    standard = [(f - mean) / spread for f in per_demo]
    ref = np.concatenate(standard)

    def score(features: np.ndarray, against: np.ndarray = ref) -> float:
        return float(np.median(nearest_distances((features - mean) / spread, against)))

    if held_out:
        positives = [score(frame_features(model, v)) for v in held_out]
        source = "held-out demonstrations"
    elif len(per_demo) >= 2:
        positives = [
            score(per_demo[i], np.concatenate(standard[:i] + standard[i + 1 :])) for i in range(len(per_demo))
        ]
        source = "training demonstrations, each scored against the others"
    else:
        raise ValueError("calibrating needs held-out demonstrations or at least two training ones")
    if synthetic is None:
        size = (int(model.cfg.image_size[0]), int(model.cfg.image_size[1]))
        synthetic = synthetic_videos(size)
    kinds = [k for k, _ in synthetic]
    negatives = [score(frame_features(model, v)) for _, v in synthetic]
    return Calibration(
        mean,
        spread,
        ref.astype(np.float32),
        choose_threshold(positives, negatives),
        np.asarray(positives),
        np.asarray(negatives),
        kinds,
        source,
        checkpoint_stamp,
    )


def calibration_path(checkpoint: str | os.PathLike) -> Path:
    """``<stem>.demo-score.npz`` beside ``<stem>.pt``."""
    path = Path(checkpoint)
    return path.with_name(path.stem + SUFFIX)


def checkpoint_stamp(checkpoint: str | os.PathLike) -> str:
    """The SHA-1 of the checkpoint's bytes: a calibration belongs to exactly one file, wherever it is copied."""
    digest = hashlib.sha1()
    with open(checkpoint, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def store_demonstrations(store, checkpoint: str | os.PathLike) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The store's demonstrations to calibrate ``checkpoint`` with: of its training tasks (the reference) and of
    its scene's held-out tasks, by the embodiments it learnt from (every expert embodiment when it names none)."""
    from studio.data.splits import load_split
    from studio.eval.evaluation import demonstration_order
    from studio.model.checkpoint_info import checkpoint_demonstrators, read_checkpoint_info, scene_of_tasks

    tasks = [str(t) for t in (read_checkpoint_info(checkpoint).get("tasks") or [])]
    scene = scene_of_tasks(tasks)
    if scene is None:
        raise ValueError(f"{checkpoint} names no tasks of one scene: its training demonstrations are unknown")
    embodiments = list(checkpoint_demonstrators(checkpoint) or _listed_demonstrators(checkpoint)) or None
    try:
        held = [t for t in load_split(scene).test if t not in tasks]
    except ValueError:
        held = []

    def videos(task_names: Sequence[str], per_task: int) -> list[np.ndarray]:
        out = []
        for task in task_names:
            filters: dict[str, Any] = {"task": task, "role": "expert"}
            if embodiments:
                filters["embodiment"] = embodiments
            # by what they are, not by when they were stored (ids carry the time): the same collection into
            # another data directory calibrates the same
            metas = sorted(store.episodes(**filters), key=demonstration_order)[:per_task]
            out += [store.load_frames(m.id) for m in metas]
        return out

    return videos(tasks, REFERENCE_PER_TASK), videos(held, HELD_OUT_PER_TASK)


def _listed_demonstrators(checkpoint: str | os.PathLike) -> tuple[str, ...]:
    """The ``demonstrators`` a shipped policy's ``NAME.json`` lists (for a file whose configuration names none)."""
    try:
        about = json.loads(Path(checkpoint).with_suffix(".json").read_text())
    except (OSError, ValueError):
        return ()
    listed = about.get("demonstrators") if isinstance(about, dict) else None
    return tuple(str(e) for e in listed) if isinstance(listed, list) else ()


def load_or_calibrate(model, checkpoint: str | os.PathLike, store=None) -> Calibration:
    """``checkpoint``'s calibration: its file when it is current (a shipped policy's is always), else made from
    ``store``'s demonstrations and written beside the checkpoint. A file made for other bytes (the checkpoint was
    retrained) is made again. ``ValueError`` when there is neither."""
    path = calibration_path(checkpoint)
    stamp = checkpoint_stamp(checkpoint)
    if path.is_file():
        try:
            found = Calibration.load(path)
        except ValueError:
            found = None
        if found is not None and found.checkpoint_stamp == stamp:
            return found
    if store is None:
        raise ValueError(f"{checkpoint} has no demonstration-score calibration ({path.name})")
    reference, held_out = store_demonstrations(store, checkpoint)
    made = calibrate(model, reference, held_out, checkpoint_stamp=stamp)
    try:
        made.save(path)
    except OSError:
        pass  # a read-only directory: the worker keeps it in memory (process_cached) instead
    return made


def score_demonstration(model, calibration: Calibration, frames: np.ndarray) -> DemoScore:
    """``frames``' score against ``calibration`` (``model``: the policy's, as it plans)."""
    return DemoScore(
        calibration.score_features(frame_features(model, frames)), calibration.threshold, calibration.source
    )


def worker_score(model, checkpoint: str, episode_id: str, frames: np.ndarray, store=None) -> dict[str, Any]:
    """A demonstration's score as a plan or rollout job reports it: :meth:`DemoScore.to_dict`, or
    ``{"unavailable": reason}`` when the checkpoint has no calibration and none can be made from ``store``.

    The calibration and each (checkpoint, demonstration)'s score are kept for the life of the worker process:
    a demonstration planned, then executed, is scored once.
    """
    from studio.eval.planners import process_cached

    st = os.stat(checkpoint)
    version = (str(checkpoint), st.st_size, st.st_mtime_ns)
    try:
        cal = process_cached(("demo-score", *version), lambda: load_or_calibrate(model, checkpoint, store))
    except ValueError as e:
        return {"unavailable": str(e)}
    return process_cached(
        ("demo-score", *version, episode_id), lambda: score_demonstration(model, cal, frames).to_dict()
    )


# ---------------------------------------------------------------------------------------------- command line
def main(argv: Sequence[str] | None = None) -> int:
    """``python -m studio.eval.demo_score CHECKPOINT --data-dir DATA``: calibrate and write ``<stem>.demo-score.npz``
    beside the checkpoint from the store's demonstrations (the policy's training tasks by the embodiments it learnt
    from, and its scene's held-out tasks), then print the figures as JSON."""
    parser = argparse.ArgumentParser(prog="python -m studio.eval.demo_score", description=main.__doc__)
    parser.add_argument("checkpoint", help="a checkpoint or policy file (.pt)")
    parser.add_argument("--data-dir", required=True, help="the store with its demonstrations")
    parser.add_argument("--out", default=None, help="where to write the calibration (default: beside it)")
    args = parser.parse_args(argv)
    from studio.data.store import EpisodeStore
    from studio.eval.planners import use_planning_threads
    from studio.model.planner import Planner

    use_planning_threads()
    planner = Planner.load(args.checkpoint)
    started = time.perf_counter()
    with EpisodeStore(args.data_dir) as store:
        reference, held_out = store_demonstrations(store, args.checkpoint)
    if not held_out:
        print("studio: no held-out demonstrations in the store; calibrating leave-one-out", file=sys.stderr)
    cal = calibrate(planner.model, reference, held_out, checkpoint_stamp=checkpoint_stamp(args.checkpoint))
    out = Path(args.out) if args.out else calibration_path(args.checkpoint)
    cal.save(out)
    figures = {
        "checkpoint": str(args.checkpoint),
        "out": str(out),
        "reference_demonstrations": len(reference),
        **cal.figures(),
        "seconds": round(time.perf_counter() - started, 1),
    }
    print(json.dumps(figures, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
