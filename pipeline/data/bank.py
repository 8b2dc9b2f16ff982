"""Reading a bank into memory: every shard checked as it is read (digest, layout, rows), and the
bank checked against the config a job runs with."""

from __future__ import annotations

import dataclasses
import io
import os
from pathlib import Path

import numpy as np

from aniformer.errors import UserError
from pipeline.data.config import BANK_SPLITS, GENERATION_FIELDS, DataConfig
from pipeline.data.manifest import Manifest, bank_file, read_manifest
from pipeline.data.shards import check_digest, read_file, read_shard


def read_faces(bank_dir: str | os.PathLike, manifest: Manifest, verify: bool = True) -> np.ndarray:
    """The bank's ``(F, 3)`` int64 faces, checked: inside the bank, a plain ``.npy`` of vertex indices in
    ``[0, num_vertices)``, and (``verify``, banks that record it) its SHA-256."""
    path = bank_file(bank_dir, manifest.faces, "faces")
    payload = read_file(path, "faces file")
    if verify and manifest.faces_sha256 is not None:
        check_digest(path, payload, manifest.faces_sha256, None)
    try:
        faces = np.load(io.BytesIO(payload), allow_pickle=False)
    except (ValueError, OSError, EOFError) as e:
        raise UserError(f"{path}: not a readable .npy of faces ({type(e).__name__})") from None
    V = manifest.num_vertices
    if (not isinstance(faces, np.ndarray) or faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0
            or faces.dtype.kind not in "iu" or faces.min() < 0 or faces.max() >= V):
        raise UserError(f"{path}: faces must be (F, 3) integer indices in [0, {V}), got "
                        f"{getattr(faces, 'shape', '?')} {getattr(faces, 'dtype', '')}")
    return faces.astype(np.int64, copy=False)


@dataclasses.dataclass
class Bank:
    """A bank in memory: ``vertices (meshes, V, 3)`` float32 in global row order, plus metadata."""

    manifest: Manifest
    faces: np.ndarray
    vertices: np.ndarray

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[1])

    @property
    def splits(self) -> dict[str, str]:
        """Every split of the bank, name -> description: those of ``BANK_SPLITS`` in its order, then any others by name."""
        table, known = self.manifest.splits, list(BANK_SPLITS)
        order = sorted(table, key=lambda s: (known.index(s) if s in known else len(known), s))
        return {s: table[s].get("description", "") for s in order}

    @property
    def non_empty_splits(self) -> list[str]:
        """The splits a pair can be drawn from: at least one motion instance and one target identity."""
        table = self.manifest.splits
        return [s for s in self.splits if table[s]["motions"] and table[s]["targets"]]

    def sequence(self, identity: int, motion: int) -> np.ndarray:
        """``(frames, V, 3)`` of an identity performing a motion instance (a view)."""
        seqs = self.manifest.sequences
        for s, (i, m) in enumerate(zip(seqs["identity"], seqs["motion"], strict=True)):
            if i == identity and m == motion:
                first = seqs["first_row"][s]
                return self.vertices[first : first + seqs["frames"][s]]
        raise KeyError(f"the bank holds no sequence of identity {identity} performing motion {motion}")


def load_bank(bank_dir: str | os.PathLike, verify: bool = True) -> Bank:
    """Read every shard of a bank into one array, each checked as it is read: its SHA-256 against the
    manifest's (``verify``, the default; each file is read once, the digest costs about 0.07 s per
    100 MB, see docs/benchmarks.md), its vertex count, rows, and the sequence, identity, motion and
    frame of every row.
    Any failure is one `UserError` line naming the file."""
    bank_dir = Path(bank_dir)
    manifest = read_manifest(bank_dir)
    V = manifest.num_vertices
    faces = read_faces(bank_dir, manifest, verify)
    seqs = manifest.sequences
    total = manifest.counts["meshes"]
    frames = np.asarray(seqs["frames"], np.int64)
    expected = {"sequence": np.repeat(np.arange(len(frames), dtype=np.int64), frames),
                "identity": np.repeat(np.asarray(seqs["identity"], np.int64), frames),
                "motion": np.repeat(np.asarray(seqs["motion"], np.int64), frames),
                "frame": np.arange(total, dtype=np.int64) - np.repeat(np.asarray(seqs["first_row"], np.int64), frames)}
    vertices = np.empty((total, V, 3), np.float32)
    flat = vertices.reshape(-1)
    for shard in manifest.shards:
        path = bank_file(bank_dir, shard["path"], "shard")
        payload = read_file(path, "shard")
        if verify:
            check_digest(path, payload, shard["sha256"], shard["bytes"])
        table = read_shard(path, payload, shard, V)
        lo, hi = shard["first_row"], shard["first_row"] + shard["rows"]
        if not all(np.array_equal(table.column(k).to_numpy(), v[lo:hi]) for k, v in expected.items()):
            raise UserError(f"{path}: its rows are not the sequences and frames the manifest places at rows "
                            f"{lo}-{hi - 1}; regenerate the bank")
        pos = lo * V * 3
        for chunk in table.column("vertices").chunks:
            values = chunk.flatten().to_numpy(zero_copy_only=False)
            flat[pos : pos + len(values)] = values
            pos += len(values)
    return Bank(manifest=manifest, faces=faces, vertices=vertices)


def check_bank_matches(manifest: Manifest, cfg: DataConfig) -> None:
    """`UserError` if a synthetic bank was generated with other generation settings than ``cfg``."""
    if manifest.kind != "synthetic":
        return
    made, wanted = manifest.config, cfg.generation_dict()
    diff = [k for k in GENERATION_FIELDS if made.get(k) != wanted[k]]
    if diff:
        shown = ", ".join(f"{k}={made.get(k)!r} (config: {wanted[k]!r})" for k in diff)
        raise UserError(f"the bank was generated with other data settings: {shown}; regenerate it or fix the config")

