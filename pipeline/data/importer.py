"""Folders of mesh frames -> a bank of the synthetic bank's format: scan the clips, plan identities,
motions and splits, then write the shards.

Layout: ``src/<identity>/<clip>/<frame files>`` (OBJ/PLY/..., one file per frame, natural sort order,
all meshes sharing one topology). A clip is one motion instance; the same clip name under several
identities means the same motion performed frame for frame (e.g. a DFAUST subject's registration and
SMPL bodies posed with its parameters). Identities that have every clip are target identities; the
others are driving identities, and each clip must be performed by exactly one of them. The action of
a clip is its name without a leading ``<driver name>_`` (DFAUST's ``50002_jumping_jacks`` ->
``jumping_jacks``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from tqdm import tqdm

from aniformer.errors import UserError
from aniformer.io.files import natural_key
from aniformer.io.mesh import MESH_SUFFIXES, load_mesh
from pipeline.data.config import check_int, derive_seed
from pipeline.data.manifest import Manifest, finish_bank, new_manifest, shard_name, write_file
from pipeline.data.plan import sequences_for, split_table
from pipeline.data.shards import shard_bytes

SHARD_BYTES = 64e6  # vertices per shard before a new one starts


def _sorted_dirs(path: Path) -> list[Path]:
    return sorted((p for p in path.iterdir() if p.is_dir()), key=lambda p: natural_key(p.name))


def scan_clips(src: Path) -> dict[str, dict[str, list[Path]]]:
    """identity -> clip -> its frame files in natural order; `UserError` for a clip without meshes."""
    clips: dict[str, dict[str, list[Path]]] = {}
    for ident in _sorted_dirs(src):
        for clip in _sorted_dirs(ident):
            files = sorted((f for f in clip.iterdir() if f.suffix.lower() in MESH_SUFFIXES),
                           key=lambda f: natural_key(f.name))
            if not files:
                raise UserError(f"{clip}: no mesh files ({', '.join(MESH_SUFFIXES)})")
            clips.setdefault(ident.name, {})[clip.name] = files
    if not clips:
        raise UserError(f"{src}: expected <identity>/<clip>/<frame files>, found no clip folders")
    return clips


def _driver_of_each_clip(src: Path, clips: dict, frames: int | None) -> tuple[list[str], list[str], dict[str, str]]:
    """(driving identities, target identities, clip -> its one driver), every clip's frames checked."""
    all_clips = sorted({c for per in clips.values() for c in per}, key=natural_key)
    targets = [i for i in clips if len(clips[i]) == len(all_clips)]
    drivers = [i for i in clips if i not in targets]
    if not drivers:
        raise UserError(
            f"{src}: every identity has every clip, so none is a driving identity (a driver performs only its own clips)"
        )
    if not targets:
        raise UserError(f"{src}: no identity has every clip, so there is no target identity")
    driver_of = {}
    for clip in all_clips:
        owners = [d for d in drivers if clip in clips[d]]
        if len(owners) != 1:
            raise UserError(
                f"clip {clip!r} is performed by {len(owners)} driving identities "
                f"({', '.join(owners) or 'none'}); each clip needs exactly one"
            )
        driver_of[clip] = owners[0]
        counts = {len(clips[i][clip]) for i in clips if clip in clips[i]}
        if len(counts) != 1:
            raise UserError(f"clip {clip!r} has different frame counts across identities: {sorted(counts)}")
        if frames is not None and counts.pop() < frames:
            raise UserError(f"clip {clip!r} has fewer than frames={frames} frames")
    return drivers, targets, driver_of


@dataclasses.dataclass


class ImportPlan:
    """What an import writes: identities (drivers, then train and test targets), motions, and the
    (identity, motion) sequences in bank order with their frame files."""

    identities: list[dict]
    motions: list[dict]
    sequences: list[tuple[int, int]]
    files: list[list[Path]]


def plan_import(src: Path, clips: dict, *, frames: int | None, test_target_fraction: float,
                unseen_instance_fraction: float, heldout_actions: Sequence[str], seed: int) -> ImportPlan:
    """Roles, splits and sequences of the scanned clips (seeded: same folders and seed, same plan)."""
    drivers, targets, driver_of = _driver_of_each_clip(src, clips, frames)
    rng = np.random.default_rng(derive_seed(seed, "import-targets"))
    n_test = min(len(targets) - 1, round(test_target_fraction * len(targets))) if len(targets) > 1 else 0
    test_targets = {targets[int(i)] for i in rng.permutation(len(targets))[:n_test]}
    names = drivers + [t for t in targets if t not in test_targets] + [t for t in targets if t in test_targets]
    identities = [
        {"id": k, "name": name, "role": "driver" if name in drivers else "target",
         "split": "seen" if name in drivers else "test" if name in test_targets else "train", "phenotype": None}
        for k, name in enumerate(names)
    ]
    index = {i["name"]: i["id"] for i in identities}
    motions = []
    for clip, driver in driver_of.items():
        action = clip[len(driver) + 1 :] if clip.startswith(driver + "_") else clip
        motions.append({"id": len(motions), "name": clip, "action": action, "instance": 0, "driver": index[driver],
                        "split": "heldout" if action in heldout_actions else "seen", "seed": None,
                        "frames": frames if frames is not None else len(clips[driver][clip])})
    candidates = [m["id"] for m in motions if m["split"] == "seen"]
    if unseen_instance_fraction > 0 and len(candidates) >= 2:
        count = min(len(candidates) - 1, max(1, round(unseen_instance_fraction * len(candidates))))
        for i in np.random.default_rng(derive_seed(seed, "import-unseen")).permutation(candidates)[:count]:
            motions[int(i)]["split"] = "unseen"
    sequences = sequences_for(identities, motions, split_table(identities, motions))
    files = []
    for ident, motion in sequences:
        clip_files = clips[names[ident]][motions[motion]["name"]]
        if frames is not None:  # that many frames, evenly spaced over the clip
            clip_files = [clip_files[int(i)] for i in np.round(np.linspace(0, len(clip_files) - 1, frames))]
        files.append(clip_files)
    return ImportPlan(identities, motions, sequences, files)


class ShardWriter:
    """Writes sequences into consecutive shards of about `SHARD_BYTES` each, recording their entries."""

    def __init__(self, out_dir: Path, manifest: Manifest):
        self.out_dir, self.manifest = out_dir, manifest
        self.shards: list[dict] = []
        self._ids: list[int] = []
        self._vertices: list[np.ndarray] = []

    def add(self, sequence_id: int, vertices: np.ndarray) -> None:
        self._ids.append(sequence_id)
        self._vertices.append(vertices)
        if sum(v.nbytes for v in self._vertices) >= SHARD_BYTES:
            self.flush()

    def flush(self) -> None:
        if not self._ids:
            return
        payload = shard_bytes(self._ids, self.manifest, self._vertices)
        path = shard_name(len(self.shards))
        write_file(self.out_dir / path, payload)
        self.shards.append({
            "path": path,
            "rows": int(sum(len(v) for v in self._vertices)),
            "sequences": [self._ids[0], self._ids[-1] + 1],
            "first_row": self.manifest.sequences["first_row"][self._ids[0]],
            "bytes": len(payload),
            "sha256": hashlib.sha256(payload).hexdigest(),
        })
        self._ids, self._vertices = [], []


def _read_sequence(files: list[Path], first: Path, faces: np.ndarray, num_vertices: int) -> np.ndarray:
    """``(frames, V, 3)`` of one sequence's files; `UserError` if a frame's topology differs from ``first``'s."""
    frames = []
    for f in files:
        v, fc = load_mesh(f)
        if len(v) != num_vertices or fc.shape != faces.shape or not np.array_equal(fc, faces):
            raise UserError(
                f"{f}: topology differs from {first} ({len(v)} vs {num_vertices} vertices "
                "or different faces); all meshes must share one topology"
            )
        frames.append(v)
    return np.stack(frames)


def import_mesh_sequences(
    src: str | os.PathLike,
    out_dir: str | os.PathLike,
    *,
    frames: int | None = None,
    test_target_fraction: float = 1 / 3,
    unseen_instance_fraction: float = 0.2,
    heldout_actions: Sequence[str] = (),
    seed: int = 0,
    progress: bool = True,
) -> Manifest:
    """Turn folders of mesh frames (see the module's docstring) into a bank in ``out_dir`` (new or empty);
    returns the manifest.

    ``frames`` samples that many frames evenly from every clip (the paper takes 30); clips of one name
    must have equal frame counts. Splits: a seeded ``test_target_fraction`` of targets are test targets,
    clips whose action is in ``heldout_actions`` are held out, and a seeded ``unseen_instance_fraction``
    of the rest.
    """
    src, out_dir = Path(src), Path(out_dir)
    if not src.is_dir():
        raise UserError(f"{src}: not a directory")
    if out_dir.exists() and any(out_dir.iterdir()):
        raise UserError(f"{out_dir} is not empty")
    if frames is not None:
        try:
            check_int("frames", frames, 1)
        except ValueError as e:
            raise UserError(str(e)) from None
    if not 0 <= test_target_fraction < 1 or not 0 <= unseen_instance_fraction < 1:
        raise UserError("test_target_fraction and unseen_instance_fraction must be in [0, 1)")
    plan = plan_import(src, scan_clips(src), frames=frames, test_target_fraction=test_target_fraction,
                       unseen_instance_fraction=unseen_instance_fraction, heldout_actions=heldout_actions, seed=seed)
    first = plan.files[0][0]
    first_vertices, faces = load_mesh(first)
    seq_frames = [len(f) for f in plan.files]
    options = {"source": str(src), "frames": frames, "test_target_fraction": test_target_fraction,
               "unseen_instance_fraction": unseen_instance_fraction, "heldout_actions": list(heldout_actions),
               "seed": seed}
    manifest = new_manifest(kind="meshes", topology=f"user:{src.name}", num_vertices=len(first_vertices),
                            identities=plan.identities, motions=plan.motions, sequences=plan.sequences,
                            frames=seq_frames, splits=split_table(plan.identities, plan.motions),
                            seeds={"seed": seed}, config=options)
    out_dir.mkdir(parents=True, exist_ok=True)
    writer = ShardWriter(out_dir, manifest)
    with tqdm(total=int(sum(seq_frames)), unit="mesh", disable=not progress, desc=f"import {src.name}") as bar:
        for s, files in enumerate(plan.files):
            writer.add(s, _read_sequence(files, first, faces, len(first_vertices)))
            bar.update(len(files))
        writer.flush()
    return finish_bank(out_dir, manifest, faces, writer.shards)
