"""Ray Train checkpoints of a run: the state a run resumes from (falling back past a truncated latest
checkpoint), the epoch its train dataset starts at, and the best one by unseen PMD."""

from __future__ import annotations

import math
from pathlib import Path

import pyarrow.fs
import ray.train

from aniformer.checkpoint import load_checkpoint
from aniformer.errors import UserError

SCORE = "pmd_unseen"


def restore_state(checkpoint: ray.train.Checkpoint) -> dict | None:
    """The state to resume from: Ray's latest checkpoint, or, if that one is unreadable (truncated by
    a crash or a full disk), the newest intact checkpoint beside it; None (start afresh, said in the
    log) if none is intact."""
    with checkpoint.as_directory() as directory:
        try:
            return load_checkpoint(directory)
        except UserError as e:
            problem = str(e)
    if not isinstance(checkpoint.filesystem, pyarrow.fs.LocalFileSystem):
        raise UserError(f"cannot resume: {problem}")
    latest = Path(checkpoint.path)
    for candidate in sorted(latest.parent.glob("checkpoint_*"), reverse=True):  # names sort by time
        if candidate != latest and candidate.is_dir():
            try:
                state = load_checkpoint(candidate)
            except UserError:
                continue
            print(f"resume: {problem}; resuming from the newest intact checkpoint, {candidate.name} "
                  f"(epoch {state['epoch']})", flush=True)
            return state
    print(f"resume: {problem}, and no other checkpoint of {latest.parent} is intact: starting afresh", flush=True)
    return None


def resume_epoch(run_dir: Path) -> int:
    """The epoch a trainer under ``run_dir`` resumes from (0 for a new run): that of the checkpoint the
    workers will restore (`restore_state` of Ray's latest), so the train dataset can start there."""
    try:
        latest = ray.train.Result.from_path(run_dir).checkpoint
    except RuntimeError:  # no such run yet
        return 0
    state = restore_state(latest) if latest else None
    return state["epoch"] if state else 0


def best_checkpoint(result: ray.train.Result) -> ray.train.Checkpoint:
    scored = [(m[SCORE], c) for c, m in (result.best_checkpoints or []) if math.isfinite(m.get(SCORE, math.nan))]
    return min(scored, key=lambda x: x[0])[1] if scored else result.checkpoint
