"""Pairs (numpy, no Ray): (driving window, target, ground truth) assembled from a bank in memory, or
made on the fly by ``aniformer.synth.stream.StreamPairs``; pair ``i`` of epoch ``e`` of a split is a pure
function of (seed, split, e, i). ``pair_source`` is the one place that chooses between them."""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from typing import Protocol, runtime_checkable

import numpy as np

from aniformer.config import from_dict
from aniformer.errors import UserError
from aniformer.synth.stream import PAIR_FIELDS, StreamPairs
from pipeline.data.bank import Bank, check_bank_matches, load_bank
from pipeline.data.config import CENTER_MODES, SHUFFLE_MODES, DataConfig, check_choice, derive_seed


@runtime_checkable
class PairSource(Protocol):
    """What every job reads pairs through (`pair_source`): a `PairSampler` over a bank, or a ``StreamPairs``.
    A new data source implements this and is returned by `pair_source` under a new ``data.source``."""

    window: int  # T, the frames of a driving window
    shuffle: str  # vertex shuffling of the target and ground truth: none | target | both

    @property
    def splits(self) -> dict[str, str]:
        """Every split, name -> description, in the pipeline's order."""

    @property
    def non_empty_splits(self) -> list[str]:
        """The splits pairs can be drawn from."""

    @property
    def faces(self) -> np.ndarray:
        """``(F, 3)`` int64: the faces of every mesh, unshuffled."""

    @property
    def num_vertices(self) -> int:
        """V, the vertices of every mesh."""

    def split(self, name: str) -> object:
        """What a split is drawn from; `UserError` if it is unknown or empty."""

    def default_pairs(self, split: str) -> int:
        """Pairs per epoch of ``split`` when a caller asks for none."""

    def batch(self, split: str, epoch: int, indices: Sequence[int] | np.ndarray, n: int | None = None) -> dict:
        """Pairs ``indices`` of epoch ``epoch`` of ``split`` (of ``n``): a pair batch (docs/architecture.md)."""

    def with_settings(self, **settings) -> PairSource:
        """The same data with other pair settings (``PAIR_FIELDS``), as an evaluation draws each model's pairs."""


def pair_source(cfg: DataConfig, bank: Bank | str | os.PathLike | None, topology: str | None = None) -> PairSource:
    """The pairs of ``cfg``: made on the fly (``source: stream``; ``bank`` unused; on ``topology``, default
    ``cfg.topology``) or drawn from ``bank``, a directory (loaded and checked against ``cfg``) or a `Bank` in
    memory (taken as it is: an evaluation may score a checkpoint on another bank than its own)."""
    if cfg.source == "stream":
        return StreamPairs(topology or cfg.topology, **cfg.pair_settings())
    if topology not in (None, cfg.topology):
        raise UserError(f"a mesh bank holds one topology ({cfg.topology}), not {topology}")
    if isinstance(bank, Bank):
        return PairSampler(bank, **cfg.pair_settings())
    return PairSampler.from_dir(bank, cfg)


class PairSampler:
    """Assembles (driving window, target, ground truth) pairs from a bank in memory; no Ray.

    ``pair_table(split, epoch, n)`` draws the pair table of an epoch (a pure function of seed, split and
    epoch); ``batch(split, epoch, indices)`` assembles pairs ``indices`` of it as numpy arrays.
    """

    def __init__(
        self,
        bank: Bank,
        *,
        window: int = 3,
        shuffle: str = "target",
        center: str = "mesh",
        seed: int = 0,
        pairs_per_epoch: int = 8000,
        eval_pairs: int = 1000,
    ):
        check_choice("shuffle", shuffle, SHUFFLE_MODES)
        check_choice("center", center, CENTER_MODES)
        self.bank, self.window, self.shuffle, self.center, self.seed = bank, window, shuffle, center, seed
        self.pairs_per_epoch, self.eval_pairs = pairs_per_epoch, eval_pairs
        m = bank.manifest
        seqs = m.sequences
        self.first_row = np.asarray(seqs["first_row"], np.int64)
        self.seq_frames = np.asarray(seqs["frames"], np.int64)
        self.seq_of = np.full((len(m.identities), len(m.motions)), -1, np.int64)
        self.seq_of[np.asarray(seqs["identity"]), np.asarray(seqs["motion"])] = np.arange(len(seqs["frames"]))
        self.driver = np.asarray([mm["driver"] for mm in m.motions], np.int64)
        self.motion_frames = np.asarray([mm["frames"] for mm in m.motions], np.int64)
        short = [mm["name"] for mm in m.motions if mm["frames"] < window]
        if short:
            raise UserError(f"window={window} is longer than motion(s) {short[:3]} of the bank")
        self._tables: dict = {}
        self._extents()

    @property
    def faces(self) -> np.ndarray:
        return self.bank.faces

    @property
    def num_vertices(self) -> int:
        return self.bank.num_vertices

    @property
    def splits(self) -> dict[str, str]:
        return self.bank.splits

    @property
    def non_empty_splits(self) -> list[str]:
        return self.bank.non_empty_splits

    def with_settings(self, **settings) -> PairSampler:
        """A sampler of the same bank in memory with other pair settings (``PAIR_FIELDS``)."""
        return type(self)(self.bank, **({k: getattr(self, k) for k in PAIR_FIELDS} | settings))

    def _extents(self, chunk: int = 4096) -> None:
        """Per-mesh bounding boxes (low, high), so centring a pair costs a subtraction."""
        verts = self.bank.vertices
        self.low = np.empty((len(verts), 3), np.float32)
        self.high = np.empty((len(verts), 3), np.float32)
        for lo in range(0, len(verts), chunk):
            block = np.ascontiguousarray(verts[lo : lo + chunk].transpose(0, 2, 1))  # (n, 3, V): fast reductions
            self.low[lo : lo + chunk] = block.min(-1)
            self.high[lo : lo + chunk] = block.max(-1)

    def _gather(self, rows: np.ndarray, perms: np.ndarray) -> np.ndarray:
        """``out[b, t, i] = vertices[rows[b, t], perms[b, i]]`` -> ``(B, T, V, 3)``, as one flat take
        (several times faster than numpy's broadcast fancy indexing)."""
        verts = self.bank.vertices
        V = verts.shape[1]
        flat = (rows[:, :, None] * V + perms[:, None, :]).reshape(-1)
        return np.take(verts.reshape(-1, 3), flat, axis=0).reshape(*rows.shape, V, 3)

    def _centre(self, rows: np.ndarray) -> np.ndarray:
        """Offsets to subtract from meshes ``rows (B, T)``, shaped ``(B, T, 1, 3)``: each mesh's
        bounding-box centre (``center="mesh"``, as ``aniformer.geometry.center_bbox``) or the whole
        window's (``"window"``)."""
        low, high = self.low[rows], self.high[rows]
        if self.center == "window":
            low, high = low.min(1, keepdims=True), high.max(1, keepdims=True)
        return ((low + high) / 2)[:, :, None, :]

    @classmethod
    def from_dir(cls, bank_dir: str | os.PathLike, cfg: DataConfig | None = None) -> PairSampler:
        """Load a bank; pair settings from ``cfg`` (else from the config the bank was made with)."""
        bank = load_bank(bank_dir)
        if cfg is None:  # the settings the bank was made with (defaults for an imported bank)
            made = bank.manifest.config if bank.manifest.kind == "synthetic" else {}
            known = {f.name for f in dataclasses.fields(DataConfig)}
            cfg = from_dict(DataConfig, {k: v for k, v in made.items() if k in known}, "the bank's config")
        else:
            check_bank_matches(bank.manifest, cfg)
        return cls(bank, **cfg.pair_settings())

    def split(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """(motion ids, target identity ids) of a split; `UserError` if unknown or empty."""
        splits = self.bank.manifest.splits
        if name not in splits:
            raise UserError(f"unknown split {name!r}; known: {', '.join(splits)}")
        motions = np.asarray(splits[name]["motions"], np.int64)
        targets = np.asarray(splits[name]["targets"], np.int64)
        if name not in self.non_empty_splits:
            raise UserError(f"split {name!r} is empty in this bank ({len(motions)} motions, {len(targets)} targets)")
        return motions, targets

    def default_pairs(self, split: str) -> int:
        return self.pairs_per_epoch if split == "train" else self.eval_pairs

    def pair_table(self, split: str, epoch: int = 0, n: int | None = None) -> dict[str, np.ndarray]:
        """The pair table of one epoch: which driving window, target pose and permutation seed."""
        n = self.default_pairs(split) if n is None else int(n)
        key = (split, int(epoch), n)
        if key not in self._tables:
            motions, targets = self.split(split)
            rng = np.random.default_rng(derive_seed(self.seed, "pairs", split, int(epoch)))
            motion = motions[rng.integers(len(motions), size=n)]
            start = (rng.random(n) * (self.motion_frames[motion] - self.window + 1)).astype(np.int64)
            target = targets[rng.integers(len(targets), size=n)]
            pose_motion = motions[rng.integers(len(motions), size=n)]
            pose_frame = (rng.random(n) * self.motion_frames[pose_motion]).astype(np.int64)
            perm_seed = rng.integers(0, 2**63 - 1, size=n, dtype=np.int64)
            table = {
                "index": np.arange(n, dtype=np.int64),
                "epoch": np.full(n, epoch, np.int64),
                "motion": motion,
                "start": start,
                "driving_identity": self.driver[motion],
                "target_identity": target,
                "target_pose_motion": pose_motion,
                "target_pose_frame": pose_frame,
                "perm_seed": perm_seed,
            }
            for name, ident, mot in (
                ("driving", self.driver[motion], motion),
                ("ground_truth", target, motion),
                ("target pose", target, pose_motion),
            ):
                if (self.seq_of[ident, mot] < 0).any():
                    raise UserError(f"split {split!r}: the bank lacks sequences for the {name} of some pairs")
            if len(self._tables) > 8:
                self._tables.clear()
            self._tables[key] = table
        return self._tables[key]

    def batch(self, split: str, epoch: int, indices: Sequence[int] | np.ndarray, n: int | None = None) -> dict:
        """Assemble pairs ``indices`` of an epoch: a dict of numpy arrays with a leading batch axis."""
        table = self.pair_table(split, epoch, n)
        idx = np.asarray(indices, np.int64)
        motion, start = table["motion"][idx], table["start"][idx]
        target = table["target_identity"][idx]
        T, verts, faces = self.window, self.bank.vertices, self.bank.faces
        steps = np.arange(T)
        drv_rows = self.first_row[self.seq_of[self.driver[motion], motion]][:, None] + start[:, None] + steps
        gt_rows = self.first_row[self.seq_of[target, motion]][:, None] + start[:, None] + steps
        pose_rows = self.first_row[self.seq_of[target, table["target_pose_motion"][idx]]] + table["target_pose_frame"][idx]
        B, V = len(idx), verts.shape[1]
        if self.shuffle == "none":
            driving, ground_truth, target_mesh = verts[drv_rows], verts[gt_rows], verts[pose_rows]
            target_faces = np.broadcast_to(faces, (B, *faces.shape))
        else:
            perms = np.empty((B, V), np.int64)
            drv_perms = np.empty((B, V), np.int64) if self.shuffle == "both" else None
            for b, s in enumerate(table["perm_seed"][idx]):
                rng = np.random.default_rng(int(s))
                perms[b] = rng.permutation(V)
                if drv_perms is not None:
                    drv_perms[b] = rng.permutation(V)
            # New vertex i = old vertex perm[i] (gathered straight from the bank); faces follow
            # through the inverse permutation.
            target_mesh = self._gather(pose_rows[:, None], perms)[:, 0]
            ground_truth = self._gather(gt_rows, perms)
            driving = verts[drv_rows] if drv_perms is None else self._gather(drv_rows, drv_perms)
            inverse = np.empty_like(perms)
            inverse[np.arange(B)[:, None], perms] = np.arange(V)
            offsets = (np.arange(B) * V)[:, None]
            target_faces = np.take(inverse.reshape(-1), offsets + faces.reshape(1, -1)).reshape(B, *faces.shape)
        if self.center != "none":  # bounding-box centres from the per-mesh extents (bit-identical)
            driving -= self._centre(drv_rows)
            ground_truth -= self._centre(gt_rows)
            target_mesh -= self._centre(pose_rows[:, None])[:, 0]
        return {
            "driving": np.ascontiguousarray(driving, np.float32),
            "target": np.ascontiguousarray(target_mesh, np.float32),
            "ground_truth": np.ascontiguousarray(ground_truth, np.float32),
            "target_faces": np.ascontiguousarray(target_faces, np.int64),
            **{k: table[k][idx] for k in ("index", "epoch", "motion", "start", "driving_identity", "target_identity")},
        }
