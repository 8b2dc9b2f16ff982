"""Evaluation: PMD (x1e-4) of models and baselines over the pair splits of a mesh bank and a noise
sweep (their Table-2-style report: ``aniformer.io.report``). numpy + torch only.

Every contender is a callable ``predict(driving (B, T, V1, 3), target (B, V2, 3), faces) -> (B, T', V2, 3)``
(``faces``: the pairs' ``target_faces`` where the sampler gives them, for models that transfer along edges)
scored on the frames it predicts (``frames``: all of a window, or the centre one for the
regression head), exactly as training reports ``pmd_<split>``, so a checkpoint's numbers here
match its training curves for the same pairs. The pairs are a ``pipeline.data.PairSampler``-like
object: anything with ``batch(split, epoch, indices, n=...)`` returning centred numpy arrays
``driving``, ``target``, ``ground_truth`` (a mesh bank's, or ``aniformer.synth.stream.StreamPairs``).
The static target (the target, unmoved) is the other trivial baseline. The copy-driver needs vertex correspondence between
driver and ground truth, so it is scored on the same pairs drawn without vertex shuffling (PMD is
invariant to permuting prediction and ground truth together, so the other models' numbers do not
depend on the shuffle except through what the model does with the order).

Noise: ``noise=a`` adds i.i.d. uniform noise in [-a, a] metres to every driving coordinate (after
centring), drawn from a generator seeded by (seed, split, level, batch), so every contender sees
the same noisy inputs at a given level.
"""

from __future__ import annotations

import functools
import math
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from aniformer.geometry import center_bbox
from aniformer.metrics import PMD_SCALE, pmd_per_frame

Predict = Callable[[torch.Tensor, torch.Tensor, torch.Tensor | None], torch.Tensor]

COPY_DRIVER, STATIC_TARGET, TRANSFER = "copy-driver", "static target", "deformation transfer"
SKINNED = "skinned transfer"
BASELINES = (COPY_DRIVER, STATIC_TARGET, TRANSFER)
DEFAULT_CLIP_FRAMES = 16  # the acceleration error's clips: half a second at 30 fps, 14 model windows
DEFAULT_CLIP_PAIRS = 64  # clips per split: each is animated window by window, ~40x a pair's cost


@dataclass
class Contender:
    """One row of the table: a name, a predictor, the window it takes and the frames it predicts."""

    name: str
    predict: Predict
    window: int
    frames: slice = field(default_factory=lambda: slice(None))
    needs_correspondence: bool = False  # copy-driver: scored on unshuffled pairs


def model_contender(name: str, model: torch.nn.Module, device: str | torch.device = "cpu") -> Contender:
    """Wrap a model built by `aniformer.models.build_model` (eval mode, no grad, fp32 output)."""
    device = torch.device(device)
    model = model.to(device).eval()

    @torch.no_grad()  # not inference_mode: roma caches tensors made here, and autograd (registration) refuses them
    def predict(driving: torch.Tensor, target: torch.Tensor, faces: torch.Tensor | None) -> torch.Tensor:
        return model(driving.to(device), target.to(device), None if faces is None else faces.to(device)).float().cpu()

    return Contender(name, predict, model.config.window, model.config.output_frames())


def copy_driver_contender(window: int, name: str = COPY_DRIVER) -> Contender:
    from aniformer.models import copy_driver

    return Contender(name, lambda driving, target, faces: copy_driver(driving, target), window, slice(None),
                     needs_correspondence=True)


def _faces_contender(name: str, transfer: Predict, window: int) -> Contender:
    """A training-free method that moves the target along the pairs' faces: needs them, and vertex correspondence."""

    def predict(driving: torch.Tensor, target: torch.Tensor, faces: torch.Tensor | None) -> torch.Tensor:
        if faces is None:
            raise ValueError(f"the {name} needs the pairs' target_faces")
        return transfer(driving, target, faces)

    return Contender(name, predict, window, slice(None), needs_correspondence=True)


def transfer_contender(window: int, name: str = TRANSFER) -> Contender:
    """The geometric prior alone (aniformer/transfer.py), no learning."""
    from aniformer.transfer import deformation_transfer

    return _faces_contender(name, deformation_transfer, window)


def skinned_transfer_contender(window: int, name: str = SKINNED) -> Contender:
    """Anny's skeleton fitted to every frame and played on the target's (aniformer/skinned_transfer.py), no
    learning: the pairs on one of Anny's topologies."""
    from aniformer.skinned_transfer import skinned_transfer

    return _faces_contender(name, skinned_transfer, window)


def static_target_contender(window: int, name: str = STATIC_TARGET) -> Contender:
    """The target, unmoved: what a model scores if it ignores the driver."""

    def predict(driving: torch.Tensor, target: torch.Tensor, faces: torch.Tensor | None) -> torch.Tensor:
        return target[:, None].expand(-1, driving.shape[1], -1, -1)

    return Contender(name, predict, window, slice(None))


def _noise_rng(seed: int, split: str, level: float, lo: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), zlib.crc32(split.encode()), int(round(level * 1e9)), int(lo)])


def pair_pmds(contenders: Sequence[Contender], sampler, split: str, *, pairs: int, batch_size: int = 16,
              noise: float = 0.0, seed: int = 0, epoch: int = 0) -> dict[str, np.ndarray]:
    """{contender name: PMD x1e4 of each of ``pairs`` pairs of ``split``}: every batch is made once
    and scored by all ``contenders`` (pair i is the same for every contender with the same window
    and sampler seed)."""
    scores: dict[str, list[np.ndarray]] = {c.name: [] for c in contenders}
    for lo in range(0, pairs, batch_size):
        batch = sampler.batch(split, epoch, np.arange(lo, min(pairs, lo + batch_size)), n=pairs)
        driving = batch["driving"]
        if noise > 0:
            driving = driving + _noise_rng(seed, split, noise, lo).uniform(-noise, noise, driving.shape).astype(np.float32)
        faces = batch.get("target_faces")
        inputs = (torch.from_numpy(np.ascontiguousarray(driving)), torch.from_numpy(batch["target"]),
                  None if faces is None else torch.from_numpy(faces))
        for c in contenders:
            pred = c.predict(*inputs)
            gt = torch.from_numpy(batch["ground_truth"])[:, c.frames]
            if pred.shape != gt.shape:
                raise ValueError(f"{c.name}: prediction {tuple(pred.shape)} vs ground truth {tuple(gt.shape)}")
            scores[c.name].append(pmd_per_frame(pred.float(), gt).mean(-1).double().numpy() * PMD_SCALE)
    return {name: np.concatenate(values) for name, values in scores.items()}


def split_pmd(contender: Contender, sampler, split: str, **kwargs) -> float:
    """Mean PMD x1e4 of ``contender`` over the pairs of ``split`` (the arguments of ``pair_pmds``)."""
    return float(pair_pmds([contender], sampler, split, **kwargs)[contender.name].mean())


class Samplers:
    """One pair sampler per (window, shuffle) over one bank in memory, built on first use."""

    def __init__(self, make: Callable[[int, str], object], shuffle: str):
        self.make, self.shuffle, self._cache = make, shuffle, {}

    def key(self, contender: Contender) -> tuple[int, str]:
        return contender.window, "none" if contender.needs_correspondence else self.shuffle

    def for_contender(self, contender: Contender):
        key = self.key(contender)
        if key not in self._cache:
            self._cache[key] = self.make(*key)
        return self._cache[key]


def evaluate_pairs(contenders: Sequence[Contender], samplers: Samplers, splits: Sequence[str], *, pairs: int,
                   batch_size: int = 16, seed: int = 0, noise: float = 0.0,
                   progress: Callable[[str, str], None] | None = None) -> dict[str, dict[str, np.ndarray]]:
    """{contender name: {split: PMD x1e4 per pair}}; contenders that take the same pairs share them."""
    groups: dict[tuple, list[Contender]] = {}
    for c in contenders:
        groups.setdefault(samplers.key(c), []).append(c)
    scores: dict[str, dict[str, np.ndarray]] = {c.name: {} for c in contenders}
    for group in groups.values():
        sampler = samplers.for_contender(group[0])
        for split in splits:
            values = pair_pmds(group, sampler, split, pairs=pairs, batch_size=batch_size, noise=noise, seed=seed)
            for c in group:
                scores[c.name][split] = values[c.name]
                if progress is not None:
                    progress(c.name, split)
    return scores


def evaluate_table(contenders: Sequence[Contender], samplers: Samplers, splits: Sequence[str], *, pairs: int,
                   batch_size: int = 16, seed: int = 0, noise: float = 0.0,
                   progress: Callable[[str, str], None] | None = None) -> dict[str, dict[str, float]]:
    """{contender name: {split: mean PMD x1e4}}."""
    scores = evaluate_pairs(contenders, samplers, splits, pairs=pairs, batch_size=batch_size, seed=seed, noise=noise,
                            progress=progress)
    return {name: {split: float(v.mean()) for split, v in row.items()} for name, row in scores.items()}


def acceleration_error(pred: torch.Tensor, ground_truth: torch.Tensor) -> torch.Tensor:
    """``(..., N, V, 3)`` clips -> ``(...)``: mean over the N - 2 inner frames and the vertices of the distance
    between predicted and true vertex accelerations (second differences), in the meshes' unit per frame²."""
    def second_difference(x: torch.Tensor) -> torch.Tensor:
        return x[..., 2:, :, :] - 2 * x[..., 1:-1, :, :] + x[..., :-2, :, :]

    return (second_difference(pred) - second_difference(ground_truth)).norm(dim=-1).mean((-2, -1))


def clip_accelerations(contenders: Sequence[Contender], clips, split: str, *, pairs: int,
                       batch_size: int = 8) -> dict[str, np.ndarray]:
    """{contender name: acceleration error (mm/frame²) of each of ``pairs`` clips of ``split``}: the
    ``clips`` sampler's windows are whole clips, which every contender animates as jobs/animate.py does,
    its own window sliding over the clip (``animate.animate_sequence``), so jitter between windows counts."""
    from aniformer.animate import animate_sequence

    scores: dict[str, list[float]] = {c.name: [] for c in contenders}
    for lo in range(0, pairs, batch_size):
        batch = clips.batch(split, 0, np.arange(lo, min(pairs, lo + batch_size)), n=pairs)
        for b in range(len(batch["driving"])):
            faces = torch.from_numpy(batch["target_faces"][b])
            truth = torch.from_numpy(batch["ground_truth"][b])
            for c in contenders:
                run = functools.partial(c.predict, faces=faces)
                pred = animate_sequence(run, batch["driving"][b], batch["target"][b], window=c.window, outputs=c.frames)
                scores[c.name].append(float(acceleration_error(torch.from_numpy(pred), truth)) * 1000)
    return {name: np.asarray(values) for name, values in scores.items()}


def noise_sweep(contenders: Sequence[Contender], samplers: Samplers, split: str, levels: Sequence[float], *,
                pairs: int, batch_size: int = 16, seed: int = 0,
                progress: Callable[[str, float], None] | None = None) -> dict[str, dict[float, float]]:
    """{contender name: {noise level (m): PMD x1e4}} on one split."""
    sweep: dict[str, dict[float, float]] = {}
    for c in contenders:
        sampler = samplers.for_contender(c)
        sweep[c.name] = {}
        for level in levels:
            sweep[c.name][level] = split_pmd(c, sampler, split, pairs=pairs, batch_size=batch_size,
                                             noise=level, seed=seed)
            if progress is not None:
                progress(c.name, level)
    return sweep


def parse_levels(text: str) -> list[float]:
    """'0,0.005,0.01' -> [0.0, 0.005, 0.01]; ValueError naming the bad item."""
    levels = []
    for item in text.split(","):
        item = item.strip()
        try:
            value = float(item)
        except ValueError:
            raise ValueError(f"noise level {item!r} is not a number") from None
        if not math.isfinite(value) or value < 0:
            raise ValueError(f"noise level {item!r} must be a finite number >= 0 (metres)")
        levels.append(value)
    if not levels:
        raise ValueError("no noise levels given")
    return sorted(set(levels))


def target_pmds(model: torch.nn.Module, stream, split: str, variants: Sequence[str], *, pairs: int,
                topology: str | None = None, device: str | torch.device = "cpu", batch_size: int = 8,
                progress: Callable[[], None] | None = None,
                refused: dict[str, list[bool]] | None = None, skinned: bool = False) -> dict[str, dict[str, np.ndarray]]:
    """{row: {variant: PMD x1e4 per pair}} on targets and drivers of other topologies
    (``synth.variants``): the model and the deformation transfer alone, each through the
    registration onto ``topology`` (default: the stream's) of the target where its faces are not
    that topology's; the copy-driver carried to the target's vertices; the static target. A
    variant with a driver of its own (``foreign_driver``) has the driver registered too, on the
    whole clip (``correspondence.register_clip``), and the model slides its window over the clip
    (``animate.animate_sequence``): every frame is scored. ``refused``, when given, gets {variant:
    per pair, whether the self-check refuses the model's result} (``trust.animation_trust``). ``skinned``: the
    skinned transfer too (``aniformer.skinned_transfer``), on the same registered templates as the other rows."""
    from aniformer.animate import animate_sequence
    from aniformer.correspondence import register_clip, register_mesh
    from aniformer.synth.stream import _body_model
    from aniformer.synth.variants import variant_pairs
    from aniformer.transfer import deformation_transfer
    from aniformer.trust import animation_trust

    topology = topology or stream.topology
    faces = torch.from_numpy(_body_model(topology).faces)
    frames = model.config.output_frames()
    predict = model_contender("model", model, device).predict
    rows = {"model": lambda d, t: predict(d, t, faces), TRANSFER: lambda d, t: deformation_transfer(d, t, faces)}
    if skinned:
        from aniformer.skinned_transfer import skinned_transfer

        rows[SKINNED] = lambda d, t: skinned_transfer(d, t, faces)
    scores = {name: {v: [] for v in variants} for name in (*rows, COPY_DRIVER, STATIC_TARGET)}

    def score(row: str, variant: str, pred: np.ndarray, truth: np.ndarray) -> None:
        error = pmd_per_frame(torch.from_numpy(np.ascontiguousarray(pred)), torch.from_numpy(truth)).mean()
        scores[row][variant].append(float(error) * PMD_SCALE)

    def drive_clip(clip: np.ndarray, target: np.ndarray) -> dict[str, np.ndarray]:
        """Each row's template posed by a whole driving ``clip (N, V, 3)`` on the template."""
        whole = {name: run(torch.from_numpy(clip[None]), torch.from_numpy(target[None]))[0].numpy()
                 for name, run in rows.items() if name != "model"}  # training-free: every frame alone
        return {"model": animate_sequence(rows["model"], clip, target, window=model.config.window, outputs=frames,
                                          device=device), **whole}

    for lo in range(0, pairs, batch_size):
        for pair in variant_pairs(stream, split, 0, range(lo, min(pairs, lo + batch_size)), variants):
            driving = torch.from_numpy(pair["driving"][None])
            for variant in variants:
                case = pair[variant]
                same = np.array_equal(case["faces"], faces.numpy())
                correspondence = None if same else register_mesh(case["target"], case["faces"], topology)
                target = case["target"] if same else correspondence.unposed_template
                driver_trust = None
                if "driving" in case:
                    driver, driver_trust = register_clip(case["driving"], case["driving_faces"], topology)
                    posed, scored = drive_clip(driver.to_template(case["driving"]), target), slice(None)
                else:
                    posed = {name: run(driving, torch.from_numpy(target[None]))[0].float().numpy()
                             for name, run in rows.items()}
                    scored = frames
                truth = case["ground_truth"][scored]
                results = {name: center_bbox(p if same else correspondence.from_template(p)) for name, p in posed.items()}
                for name, result in results.items():
                    score(name, variant, result, truth)
                score(COPY_DRIVER, variant, case["copy_driver"][scored], truth)
                score(STATIC_TARGET, variant, np.broadcast_to(case["target"], truth.shape), truth)
                if refused is not None:
                    trust = animation_trust(results["model"], case["target"], case["faces"], correspondence, driver_trust)
                    refused.setdefault(variant, []).append(not trust.ok)
            if progress is not None:
                progress()
    return {row: {v: np.asarray(x) for v, x in values.items()} for row, values in scores.items()}
