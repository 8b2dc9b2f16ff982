"""Training and evaluation pairs made on the fly: fresh Anny bodies doing smooth motion (no Ray).

A bank holds a finite set of bodies and clips; a *stream* draws every pair anew. Pair ``i`` of
epoch ``e`` of a split is a pure function of ``(seed, split, e, i)``:

- a driving identity and a target identity, fresh phenotypes from the split's body distribution;
- a driving window of ``T`` frames from ``poses.sample_windows`` (the split's families and
  orientations); the ground truth is the target identity performing the same window;
- the target mesh: the target identity at rest (a quarter of the pairs, as users' characters
  come) or in one frame of an independent window of the same split.

Splits are seeded apart: ``train`` from the training seed stream, ``seen``/``unseen`` (the
validation that picks checkpoints) from a validation stream, and the test splits from a test
stream, so no test body, window or pair is trained or tuned on. See ``STREAM_SPLITS``.

Batches only vectorise the work (one Anny call per batch); the draws of a pair come from its own
generators, so a pair does not depend on which batch it is assembled in (Anny's float32 skinning
can differ in the last bit with the batch size, far below anything PMD resolves).
"""

from __future__ import annotations

import functools
import types
import zlib
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from aniformer.synth.motions import ACTIONS
from aniformer.synth.poses import sample_windows

#: Library actions never trained on (with the ``kick`` family: the held-out action split).
HELDOUT_ACTIONS: tuple[str, ...] = ("jumping_jacks", "punching", "chicken_wings", "one_leg_loose")
TRAIN_ACTIONS: tuple[str, ...] = tuple(a for a in ACTIONS if a not in HELDOUT_ACTIONS)
TRAIN_FAMILIES = {"random": 0.3, "bend": 0.1, "crouch": 0.15, "locomotion": 0.15, "library": 0.15, "blend": 0.15}
TRAIN_ORIENTATIONS = {"upright": 0.5, "tilted": 0.2, "any": 0.3}
UPRIGHT = {"upright": 1.0}
REST_TARGET_FRACTION = 0.25
BODIES = ("mixed", "broad", "extreme", "mismatch")
CORNER_BODIES = 0.2  # of `broad` bodies: near the corners of the shape space, as `extreme` draws them


@dataclass(frozen=True)
class StreamSplit:
    """What the pairs of a split are drawn from; ``stream`` keeps the seeds of splits apart."""

    families: dict[str, float]
    orientations: dict[str, float]
    bodies: str  # mixed | extreme | mismatch (driver and target at opposite extremes)
    stream: str  # train | val | test
    description: str
    actions: tuple[str, ...] = TRAIN_ACTIONS
    rest_targets: float = REST_TARGET_FRACTION  # fraction of targets at rest, the others in a pose of the split


#: The stream's splits (a bank's are ``pipeline.data.BANK_SPLITS``).
STREAM_SPLITS: dict[str, StreamSplit] = {
    "train": StreamSplit(TRAIN_FAMILIES, TRAIN_ORIENTATIONS, "broad", "train", "the training distribution"),
    "seen": StreamSplit(TRAIN_FAMILIES, TRAIN_ORIENTATIONS, "mixed", "val",
                        "validation: the training distribution, fresh bodies and windows"),
    "unseen": StreamSplit(TRAIN_FAMILIES, {"any": 1.0}, "extreme", "val",
                          "validation (picks the best checkpoint): extreme bodies, any orientation"),
    "random_poses": StreamSplit({"random": 1.0}, UPRIGHT, "mixed", "test", "test: random poses within joint limits"),
    "rotated": StreamSplit(TRAIN_FAMILIES, {"tilted": 0.3, "any": 0.7}, "mixed", "test",
                           "test: bodies lying, tilted, upside down, turning"),
    "heldout_actions": StreamSplit({"library": 0.6, "kick": 0.4}, UPRIGHT, "mixed", "test",
                                   f"test: action families never trained on (kicks, {', '.join(HELDOUT_ACTIONS)})",
                                   HELDOUT_ACTIONS),
    "locomotion": StreamSplit({"locomotion": 1.0}, UPRIGHT, "mixed", "test", "test: walking and running, turning"),
    "crouch": StreamSplit({"crouch": 1.0}, UPRIGHT, "mixed", "test", "test: deep squats and kneeling"),
    "extreme_bodies": StreamSplit(TRAIN_FAMILIES, UPRIGHT, "extreme", "test",
                                  "test: driver and target at the extremes of the adult shape space"),
    "build_mismatch": StreamSplit(TRAIN_FAMILIES, UPRIGHT, "mismatch", "test",
                                  "test: driver and target of opposite builds (short/tall, thin/heavy, weak/muscular)"),
    "characters": StreamSplit(TRAIN_FAMILIES, UPRIGHT, "mixed", "test",
                              "test: targets at rest, as characters come (the foreign-topology evaluation)",
                              rest_targets=1.0),
}
TEST_SPLITS = tuple(name for name, s in STREAM_SPLITS.items() if s.stream == "test")


def _generator(seed: int, *keys: int | str) -> np.random.Generator:
    return np.random.default_rng([int(seed), *(zlib.crc32(k.encode()) if isinstance(k, str) else int(k) for k in keys)])


@functools.cache
def _shape_distribution():
    from anny.shape_distribution import SimpleShapeDistribution

    from aniformer.synth.bodies import ADULT_AGE_YEARS, PHENOTYPE_KEYS

    spec = types.SimpleNamespace(dtype=torch.float64, device=torch.device("cpu"), phenotype_labels=list(PHENOTYPE_KEYS))
    low, high = (torch.tensor(v, dtype=torch.float64) for v in ADULT_AGE_YEARS)
    return SimpleShapeDistribution(spec, morphological_age_distribution=torch.distributions.Uniform(low, high))


def _calibrated_adults(rngs: Sequence[np.random.Generator]) -> dict[str, np.ndarray]:
    """Anny's ``SimpleShapeDistribution`` (WHO-calibrated; adults of 18-70 years) for two bodies
    per rng, vectorised: ages and genders from each rng, then Beta draws from it at the batch's
    conditional parameters."""
    from aniformer.synth.bodies import ADULT_AGE_YEARS

    dist = _shape_distribution()
    draws = np.stack([rng.random((2, 2)) for rng in rngs])  # (B, 2 bodies, [age, gender])
    morph_age = ADULT_AGE_YEARS[0] + (ADULT_AGE_YEARS[1] - ADULT_AGE_YEARS[0]) * draws[..., 0]
    age = dist.morphological_age_mapping.morphological_to_anny_age(torch.from_numpy(morph_age.reshape(-1)))
    gender = draws[..., 1]
    out = {"age": age.numpy().reshape(-1, 2), "gender": gender}
    for key in ("height", "weight", "muscle", "proportions"):
        params = []
        for sex in ("boys", "girls"):
            a, b = getattr(dist, f"{sex}_conditional_{key}_distribution").get_distribution_params(age)
            params.append(np.stack([a.numpy(), b.numpy()], -1).reshape(-1, 2, 2))
        alpha_beta = np.where((gender <= 0.5)[..., None], params[0], params[1])
        out[key] = np.stack([rng.beta(ab[:, 0], ab[:, 1]) for rng, ab in zip(rngs, alpha_beta, strict=True)])
    return out


def sample_body_pairs(rngs: Sequence[np.random.Generator], bodies: str) -> np.ndarray:
    """(driver, target) phenotypes ``(B, 2, 6)`` float32 (``bodies.PHENOTYPE_KEYS`` order), one
    pair per rng.

    ``mixed``: 60% Anny's WHO-calibrated adults, 40% with muscle, weight, height and proportions
    uniform in [0, 1] (the extremes of the shape space); ``extreme``: each of those and gender
    within 0.12 of 0 or 1; ``mismatch``: like ``extreme``, the target at the opposite corner of
    the driver in muscle, weight and height; ``broad`` (training): ``mixed``, with each body
    independently an ``extreme`` one at rate ``CORNER_BODIES``: in ``mixed`` a short target under a
    tall driver is rare, and the learned correction was worse than none there."""
    from aniformer.synth.bodies import PHENOTYPE_KEYS

    pheno = _calibrated_adults(rngs)
    free = ("muscle", "weight", "height", "proportions")
    if bodies in ("mixed", "broad"):
        uniform = np.stack([rng.random(2) < 0.4 for rng in rngs])
        values = np.stack([rng.random((2, 4)) for rng in rngs])
        for j, k in enumerate(free):
            pheno[k] = np.where(uniform, values[..., j], pheno[k])
    if bodies != "mixed":
        corner = np.stack([rng.random((2, 5)) < 0.5 for rng in rngs])
        if bodies == "mismatch":
            corner[:, 1, :3] = ~corner[:, 0, :3]  # muscle, weight, height opposite
        spread = 0.12 * np.stack([rng.random((2, 5)) for rng in rngs])
        values = np.where(corner, 1 - spread, spread)
        extreme = np.stack([rng.random(2) < CORNER_BODIES for rng in rngs]) if bodies == "broad" else True
        for j, k in enumerate((*free, "gender")):
            pheno[k] = np.where(extreme, values[..., j], pheno[k])
    return np.clip(np.stack([pheno[k] for k in PHENOTYPE_KEYS], axis=-1), 0, 1).astype(np.float32)


@functools.cache
def _body_model(topology: str):
    from aniformer.synth.bodies import BodyModel

    return BodyModel(topology)  # one per topology and process


def _choose(rng: np.random.Generator, weights: dict[str, float]) -> str:
    names = list(weights)
    p = np.array([weights[n] for n in names], float)
    return names[int(rng.choice(len(names), p=p / p.sum()))]


def centre(vertices: np.ndarray, mode: str) -> np.ndarray:
    """Subtract bounding-box centres: of each mesh (``mesh``), of each window (``window``), or none.
    ``vertices (B, T, V, 3)``."""
    if mode == "none":
        return vertices
    axes = (-2,) if mode == "mesh" else (1, 2)
    low, high = vertices.min(axis=axes, keepdims=True), vertices.max(axis=axes, keepdims=True)
    return vertices - (low + high) / 2


# The settings that shape the pairs drawn from any source (a stream, or a bank's `pipeline.data.PairSampler`).
PAIR_FIELDS = ("window", "shuffle", "center", "seed", "pairs_per_epoch", "eval_pairs")


class StreamPairs:
    """Pairs of the ``STREAM_SPLITS`` made on demand; a ``pipeline.data.PairSource`` like ``PairSampler``.

    ``batch(split, epoch, indices)`` returns numpy arrays ``driving (B, T, V, 3)``, ``target
    (B, V, 3)``, ``ground_truth (B, T, V, 3)``, ``target_faces (B, F, 3)`` and int64 ``index``,
    ``epoch``. Picklable and cheap to ship: the Anny model is built on first use in a process.
    """

    block_pairs = 64  # pairs per Ray Data block: ~5 ms each to make, so small blocks keep several CPUs busy

    def __init__(self, topology: str, *, window: int = 3, shuffle: str = "none", center: str = "mesh", seed: int = 0,
                 pairs_per_epoch: int = 8000, eval_pairs: int = 1000):
        if shuffle != "none":  # one topology for driver and target: vertex i is the same body point in both
            raise ValueError(f"a stream's pairs are never shuffled, got shuffle={shuffle!r}")
        self.topology, self.window, self.shuffle, self.center, self.seed = topology, window, shuffle, center, seed
        self.pairs_per_epoch, self.eval_pairs = pairs_per_epoch, eval_pairs

    def with_settings(self, **settings) -> StreamPairs:
        """The same stream with other pair settings (``PAIR_FIELDS``)."""
        return type(self)(self.topology, **({k: getattr(self, k) for k in PAIR_FIELDS} | settings))

    @property
    def body(self):
        return _body_model(self.topology)

    @property
    def faces(self) -> np.ndarray:
        return self.body.faces

    @property
    def num_vertices(self) -> int:
        return self.body.num_vertices

    @property
    def splits(self) -> dict[str, str]:
        return {name: split.description for name, split in STREAM_SPLITS.items()}

    @property
    def non_empty_splits(self) -> list[str]:
        return list(STREAM_SPLITS)  # every split draws fresh bodies and motion

    def split(self, name: str) -> StreamSplit:
        from aniformer.errors import UserError

        if name not in STREAM_SPLITS:
            raise UserError(f"unknown split {name!r}; known: {', '.join(STREAM_SPLITS)}")
        return STREAM_SPLITS[name]

    def default_pairs(self, split: str) -> int:
        return self.pairs_per_epoch if split == "train" else self.eval_pairs

    def draws(self, split: str, epoch: int, indices: Sequence[int] | np.ndarray) -> dict:
        """What pairs ``indices`` of ``split`` in ``epoch`` are made of, before posing: ``identities``
        ``(B, 2, 6)`` (driver, target), ``motion (B, T, bones, 3)`` and ``translation (B, T, 3)`` of
        the driving window, ``target_pose (B, bones, 3)``."""
        spec = self.split(split)
        idx = np.asarray(indices, np.int64)
        keys = [(self.seed, "stream", spec.stream, split, int(epoch), int(i)) for i in idx]
        pair_rngs = [_generator(*k, "pair") for k in keys]
        drive_rngs = [_generator(*k, "driving") for k in keys]
        pose_rngs = [_generator(*k, "target pose") for k in keys]
        bodies = sample_body_pairs(pair_rngs, spec.bodies)
        rest = np.array([rng.random() < spec.rest_targets for rng in pair_rngs])
        choices = [(_choose(r, spec.families), _choose(r, spec.orientations)) for r in pair_rngs]
        pose_choices = [(_choose(r, spec.families), _choose(r, spec.orientations)) for r in pair_rngs]
        labels = self.body.bone_labels
        rotvecs, translation = sample_windows(*zip(*choices), drive_rngs, self.window, labels, spec.actions)
        pose, _ = sample_windows(*zip(*pose_choices), pose_rngs, 1, labels, spec.actions)
        pose[rest] = 0.0
        return {"identities": bodies, "motion": rotvecs, "translation": translation, "target_pose": pose[:, 0]}

    def batch(self, split: str, epoch: int, indices: Sequence[int] | np.ndarray, n: int | None = None) -> dict:
        """Pairs ``indices`` of ``split`` in ``epoch`` (``n``, the epoch's size, is not needed: a pair
        depends on its index alone)."""
        idx = np.asarray(indices, np.int64)
        body = self.body
        threads = torch.get_num_threads()
        torch.set_num_threads(1)  # Ray Data runs several of these tasks on a few cores
        try:
            draws = self.draws(split, epoch, idx)
            meshes = pose_pairs(body, draws)
        finally:
            torch.set_num_threads(threads)
        driving, ground_truth, target = (centre(m, self.center) for m in meshes)
        B = len(idx)
        return {
            "driving": np.ascontiguousarray(driving, np.float32),
            "target": np.ascontiguousarray(target[:, 0], np.float32),
            "ground_truth": np.ascontiguousarray(ground_truth, np.float32),
            "target_faces": np.ascontiguousarray(np.broadcast_to(body.faces, (B, *body.faces.shape)), np.int64),
            "index": idx,
            "epoch": np.full(B, epoch, np.int64),
        }


def pose_pairs(body, draws: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The meshes of ``StreamPairs.draws`` on ``body``'s topology, uncentred: driving and ground
    truth ``(B, T, V, 3)``, target ``(B, 1, V, 3)`` (one Anny call for all)."""
    bodies, rotvecs, translation = draws["identities"], draws["motion"], draws["translation"]
    B, T, bones = rotvecs.shape[:3]
    identities = np.concatenate([np.repeat(bodies[:, 0], T, 0), np.repeat(bodies[:, 1], T, 0), bodies[:, 1]])
    motion = rotvecs.reshape(B * T, bones, 3)
    offsets = translation.reshape(B * T, 3)
    meshes = body.pose(identities, np.concatenate([motion, motion, draws["target_pose"]]),
                       np.concatenate([offsets, offsets, np.zeros((B, 3), np.float32)]))
    V = meshes.shape[1]
    return (meshes[: B * T].reshape(B, T, V, 3), meshes[B * T : 2 * B * T].reshape(B, T, V, 3),
            meshes[2 * B * T :].reshape(B, 1, V, 3))
