"""Synthetic sequences: Anny bodies of the plan's identities performing its motion instances. Pure
functions of (manifest, sequence ids), so a shard's bytes do not depend on which worker makes it."""

from __future__ import annotations

import fcntl
import functools
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from aniformer.synth.bodies import BodyModel
from aniformer.synth.motions import sample_motion
from pipeline.data.manifest import Manifest
from pipeline.data.shards import shard_bytes


def pose_sequence(body, phenotype: Sequence[float], motion) -> np.ndarray:
    """``(frames, V, 3)``: one identity performing one motion (exactly how the bank is made).

    One call per whole clip: Anny's float32 output can differ in the last bit with the batch
    size, so reproducing a bank mesh bit for bit means posing the whole clip the same way."""
    frames = len(motion.rotvecs)
    identity = np.repeat(np.asarray(phenotype, np.float32)[None], frames, axis=0)
    return body.pose(identity, motion.rotvecs, motion.translation)


@functools.lru_cache(maxsize=256)


def _motion(action: str, seed: int, frames: int, topology: str):
    return sample_motion(action, seed, BodyModel(topology).bone_labels, frames=frames)


def motion_of(manifest: Manifest, motion_id: int):
    """The ``aniformer.synth.motions.Motion`` of a synthetic bank's motion instance."""
    m = manifest.motions[motion_id]
    return _motion(m["action"], int(m["seed"]), int(m["frames"]), manifest.topology)


def generate_shard(manifest: Manifest, sequence_ids: Sequence[int]) -> bytes:
    """Parquet bytes of one shard of a synthetic bank (a pure function of its arguments)."""
    torch.set_num_threads(1)  # thread count can change float summation order: keep bytes fixed
    body = body_model(manifest.topology)
    seqs = manifest.sequences
    vertices = [
        pose_sequence(
            body,
            manifest.identities[seqs["identity"][s]]["phenotype"],
            motion_of(manifest, seqs["motion"][s]),
        )
        for s in sequence_ids
    ]
    return shard_bytes(sequence_ids, manifest, vertices)


def body_model(topology: str):
    """The process's body model; cold Anny builds (minutes, a large cache) are serialised by a
    file lock so that concurrent workers on one machine don't all build it at once."""
    with open(Path(tempfile.gettempdir()) / "aniformer-anny-build.lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            return BodyModel(topology)
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)

