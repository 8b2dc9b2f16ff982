"""Peak memory of one training step, predicted from the layer plan, before anything is allocated.

Used by the sweeps (`pipeline/tune.py`) to know whether a trial fits a worker *before* it starts:
a trial predicted over the per-worker limit gets a smaller batch with gradient accumulation, or is
skipped. Pure: torch only (parameters are counted on the "meta" device, which allocates nothing).

What a training step holds at its peak (the end of the forward pass / start of backward)::

    static       parameters + Adam's two moments (2x)  [+ 1x DDP buckets, >1 worker]; the
                 gradients (1x) grow while activations are released: max(them, the dynamic part)
    activations  every tensor autograd saves for backward, counted layer by layer below
    workspace    transients of the backward pass: a few (B, T, V, C_max) gradient buffers
    inputs       the batch (driving, target, ground truth, faces) and the prefetched ones
    overhead     what the process holds before the step: interpreter + torch + Ray on CPU,
                 the CUDA context and allocator slack on a GPU

Activations dominate. With `M = B*T*V` vertices-in-frames, in units of `M*C` elements:

    extractor layer c (Table 3)    Linear out (the norm's saved input, fp32), x - mean (fp32),
                                   ReLU out                                         3 per layer
    encoder stage C (Tables 4, 6)  proj out, q, k|v (2), SDPA out, gated residual   6
                                   SPAdaIN resblock: 3 paths x (x - mean, normalised,
                                   modulated, ReLU out) + the sum                   13
                                   (+ 3 per-vertex modulations (B, 1, V, C), + the SDPA log-sum-exp
                                   (B*T, heads, V) -- memory-linear in V: no V x V map)
    temporal attention (switch)    q|k|v (3), SDPA out, gated residual              5
    losses (eq. 4-6)               edge gathers of eq. 5: ~(9 + 3) * B*T*F floats

Under bf16/fp16 autocast the Linear outputs are 2 bytes but instance norm keeps its statistics and
saved tensors in fp32 (`aniformer.model.instance_norm`); the count keeps the two classes apart.

Calibration. The count of saved tensors matches autograd's own (`saved_tensors_hooks`) within a
few per cent (tests/test_memory.py). On CPU, peak RSS is larger than the peak of live tensors:
glibc's malloc raises its mmap threshold dynamically, after which freed activation buffers stay
in the heap, fragmented. `ALLOCATOR_FACTOR["cpu"]` (fitted by bench/memory_calibration.py, error
in docs/benchmarks.md) scales the dynamic part for that; with `MALLOC_MMAP_THRESHOLD_` set, RSS
follows the live tensors and the factor is 1. On CUDA, `torch.cuda.max_memory_allocated`
counts live tensors only: on an H100 it was 0.96-0.98 of the count (9 configs, bf16/fp16/fp32,
checkpointed or not); the factor there is headroom for what the caching allocator reserves beyond that.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch

GiB = 2**30

# Bytes per element of the compute dtype (autocast) for each training precision.
PRECISION_BYTES = {"fp32": 4, "bf16": 2, "fp16": 2}

# Peak memory over the live-tensor peak of the dynamic part (activations + workspace + inputs).
# "cpu": peak RSS under glibc's default malloc, which raises its mmap threshold as large buffers
#   are freed, after which freed activation buffers stay resident (fragmented heap): RSS grows over
#   the first ~8 steps to 1.5-1.8x the live peak (bench/memory_calibration.py, docs/benchmarks.md).
# "cpu-mmap": the same with MALLOC_MMAP_THRESHOLD_ set (large buffers mmapped and returned on free):
#   peak RSS is the live peak, within +-5%.
# "cuda": torch.cuda.max_memory_allocated counts live tensors; measured on an H100 it is 0.96-0.98x
#   the count, so 1.1 over-predicts it by 11-15% (docs/benchmarks.md): headroom kept for the caching
#   allocator's reserved-but-unallocated blocks (max_memory_reserved, printed by the calibration).
ALLOCATOR_FACTOR = {"cpu": 1.7, "cpu-mmap": 1.0, "cuda": 1.1}


def allocator(device: str) -> str:
    """The ALLOCATOR_FACTOR key for `device` in this process's environment."""
    import os

    if str(device).startswith("cuda"):
        return "cuda"
    return "cpu-mmap" if os.environ.get("MALLOC_MMAP_THRESHOLD_") else "cpu"


# What the process holds before the first step, for gating a whole worker against a limit.
# CPU: a Ray Train worker with torch, Ray Data and the loop's code loaded (peak_memory_gb of a
# tiny trial minus its predicted step). CUDA: the CUDA context + cuBLAS/cuDNN workspaces (these
# are outside max_memory_allocated but inside the card's memory).
PROCESS_OVERHEAD_GB = {"cpu": 0.8, "cuda": 0.75}


@dataclass(frozen=True)
class MemoryEstimate:
    """A predicted training-step peak, in bytes, by part (see the module docstring)."""

    parameters: int
    gradients: int
    optimizer: int
    ddp_buckets: int
    activations: int
    workspace: int
    inputs: int
    allocator_factor: float
    overhead: int

    @property
    def static(self) -> int:
        return self.parameters + self.gradients + self.optimizer + self.ddp_buckets

    @property
    def dynamic(self) -> int:
        """Activations + workspace + inputs, scaled by the allocator factor."""
        return int(self.allocator_factor * (self.activations + self.workspace + self.inputs))

    @property
    def step(self) -> int:
        """What one training step adds to a process: what the calibration measures.

        Gradients appear during backward while the activations they come from are released, so
        the peak holds the larger of the two, not their sum (Adam's moments live throughout).
        """
        held = self.parameters + self.optimizer + self.ddp_buckets
        return held + max(self.dynamic, self.gradients)

    @property
    def total(self) -> int:
        """The whole worker: the step plus the process overhead; what the sweep gate compares."""
        return self.step + self.overhead

    @property
    def step_gb(self) -> float:
        return self.step / GiB

    @property
    def total_gb(self) -> float:
        return self.total / GiB

    def to_dict(self) -> dict:
        return {**dataclasses.asdict(self), "step_gb": self.step_gb, "total_gb": self.total_gb}


class _Ledger:
    """Saved-tensor elements by byte class: `compute` (autocast dtype) and `fp32`."""

    def __init__(self):
        self.compute = 0
        self.fp32 = 0

    def add(self, elements: int, fp32: bool = False) -> None:
        if fp32:
            self.fp32 += int(elements)
        else:
            self.compute += int(elements)

    def bytes(self, compute_bytes: int) -> int:
        return self.compute * compute_bytes + self.fp32 * 4

    def merge(self, other: _Ledger) -> None:
        self.compute += other.compute
        self.fp32 += other.fp32


def _extractor(points: int, channels: tuple[int, ...]) -> _Ledger:
    """FeatureExtractor over `points` vertices-in-frames: Linear -> InstanceNorm -> ReLU per layer."""
    ledger = _Ledger()
    ledger.add(points * 3)  # the xyz input, saved by the first Linear
    for c in channels:
        ledger.add(points * c, fp32=True)  # Linear out: saved by var_mean (its fp32 copy under autocast)
        ledger.add(points * c, fp32=True)  # x - mean, saved by the multiply with rsqrt(var)
        ledger.add(points * c)  # ReLU out (saved by ReLU and by the next Linear)
    return ledger


def _kept(elements: int, fp32: bool = False) -> _Ledger:
    ledger = _Ledger()
    ledger.add(elements, fp32)
    return ledger


def _resblock(m: int, c: int, modulation: int, mixed: bool) -> _Ledger:
    """SPAdaINResBlock on `m` vertices-in-frames of width c; `modulation` = elements of one (B, 1, V, C) scale."""
    ledger = _Ledger()
    for path in range(3):  # norm1 -> fc1, norm2 -> fc2, norm_skip -> fc_skip
        second = path == 1  # its input is fc1's ReLU output (compute dtype): norm copies it to fp32
        if second and mixed:
            ledger.add(m * c, fp32=True)
        ledger.add(m * c, fp32=True)  # x - mean
        ledger.add(m * c, fp32=not second)  # normalised (kept in its input's dtype), saved by the scale multiply
        ledger.add(modulation)  # to_scale(target), saved by the same multiply
        ledger.add(m * c)  # modulated (+ shift), saved by the fc (as its compute-dtype copy)
        ledger.add(m * c)  # ReLU out
    ledger.add(m * c)  # out + skip: the stage's output, saved by the next Linear
    return ledger


# A checkpointed part of a model: (what it saves while it runs, what is kept of it: its output).
_Stage = tuple[_Ledger, _Ledger]


def count_activations(model_name: str, config, batch: int, vertices: tuple[int, int], precision: str = "fp32",
                      faces: int | None = None, activation_checkpointing: bool = False) -> tuple[int, int]:
    """(saved-activation bytes, workspace bytes) of one forward + loss for `batch` windows.

    `vertices` = (V1 driving, V2 target); `faces` = triangles of the target (default 2*V2, a closed mesh).
    With `activation_checkpointing` autograd keeps the outputs of the checkpointed parts only (each
    stage's attention and block, NPT's blocks; the feature extractors' outputs go into an add or
    concat, which keeps nothing); the peak is that of the largest part rerun in backward, with the
    outputs kept for the parts before it.
    """
    compute_bytes = PRECISION_BYTES[precision]
    mixed = precision != "fp32"
    B, (V1, V2) = batch, vertices
    T = config.window
    F = faces if faces is not None else 2 * V2
    ledger = _Ledger()  # what is saved outside the checkpointed parts
    ext = tuple(config.extractor_channels)
    if model_name == "npt":
        stages, out_frames = _npt_stages(ledger, config, B * T, V1, V2, ext, mixed)
    elif model_name == "aniformer":
        stages, out_frames = _aniformer_stages(ledger, config, B, T, V1, V2, ext, mixed)
    else:
        raise ValueError(f"no memory model for model {model_name!r}")
    ledger.merge(_prediction_and_losses(B * out_frames * V2, B * out_frames * F))
    parts = 0
    if activation_checkpointing:
        parts = _checkpointed_peak(stages, compute_bytes)
    else:
        for part, _ in stages:
            ledger.merge(part)
    activations = ledger.bytes(compute_bytes) + parts
    # backward transients: the gradient of the widest activation and its fp32 companions
    c_max = max((*ext, *getattr(config, "channels", ())))
    workspace = 3 * B * T * max(V1, V2) * c_max * 4
    return activations, workspace


def _npt_stages(ledger: _Ledger, config, S: int, V1: int, V2: int, ext: tuple[int, ...],
                mixed: bool) -> tuple[list[_Stage], int]:
    """NPT on `S` = B*T samples (frames are samples): its parts, and the frames it predicts per window."""
    m1, m2 = S * V1, S * V2
    stages: list[_Stage] = [(_extractor(m1, ext), _Ledger())]  # output not kept: an add / concat takes it
    if V1 != V2:
        ledger.add(m1 * ext[-1], fp32=True)  # amax saves its input
    ledger.add(m2 * (ext[-1] + 3))  # [pose, identity] concatenated, saved by the first projection
    for c in config.channels:
        ledger.add(m2 * c)  # projection out (the block's input)
        stages.append((_resblock(m2, c, S * V2 * c, mixed), _kept(m2 * c)))
    return stages, config.window


def _aniformer_stages(ledger: _Ledger, config, B: int, T: int, V1: int, V2: int, ext: tuple[int, ...],
                      mixed: bool) -> tuple[list[_Stage], int]:
    """AniFormer: its parts (extractors, then each encoder stage's mix and block), and the frames it predicts."""
    cf = ext[-1]
    m1, m2 = B * T * V1, B * T * V2
    stages: list[_Stage] = [(_extractor(m1, ext), _Ledger())]  # output not kept: an add / concat takes it
    ledger.add(m1 * cf)  # features + temporal embedding (eq. 1), saved by the first proj / to_kv
    cross = config.attention == "cross"
    if cross:
        stages.append((_extractor(B * V2, ext), _Ledger()))
        ledger.add(m2 * cf)  # the expanded target features, materialised for the first proj
    elif config.pool_driving or V1 != V2:
        ledger.add(m1 * cf, fp32=True)  # amax saves its input
        ledger.add(m2 * cf)  # the broadcast code, materialised for the first proj
    for c, heads in zip(config.channels, config.stage_heads()):
        stages.append((_stage_mix(m1 if cross else m2, m2, c, heads, config.temporal == "attention"),
                       _kept(m2 * c, fp32=True)))  # the fp32 residual: the block's input
        stages.append((_resblock(m2, c, B * V2 * c, mixed), _kept(m2 * c)))
    if config.head == "regression":
        ledger.add(2 * B * V2 * config.channels[-1])  # the head's Linear in / ReLU out on the frame-averaged features
        return stages, 1
    return stages, T


def _stage_mix(kv: int, m: int, c: int, heads: int, temporal_attention: bool) -> _Ledger:
    """EncoderStage.mix on `m` vertices-in-frames of width c: width change and attention (keys, values
    from `kv` vertices-in-frames), then attention across frames if `temporal_attention`."""
    ledger = _Ledger()
    ledger.add(m * c)  # proj out
    ledger.add(m * c)  # q
    ledger.add(kv * 2 * c)  # k | v
    ledger.add(m * c)  # SDPA out
    ledger.add(m * heads, fp32=True)  # SDPA log-sum-exp: linear in V, no V x V map
    ledger.add(m * c, fp32=True)  # x + gamma * attention (fp32: gamma promotes it)
    if temporal_attention:
        ledger.add(m * c)  # compute-dtype copy of the residual for to_qkv (0 in fp32: it is the residual)
        ledger.add(m * 3 * c)  # q | k | v across frames
        ledger.add(m * c)  # SDPA out
        ledger.add(m * heads, fp32=True)
        ledger.add(m * c, fp32=True)  # the gated residual
    return ledger


def _prediction_and_losses(mo: int, edges: int) -> _Ledger:
    """The output head's xyz and the losses, for `mo` predicted vertices-in-frames and `edges` = B*frames*F."""
    ledger = _Ledger()
    ledger.add(3 * mo * 3)  # xyz out, tanh out, 2 * tanh (the prediction)
    # losses in fp32: pred.float(), rec's difference, eq. 4's frame differences, eq. 5's edge gathers
    ledger.add(mo * 3 * 4, fp32=True)
    ledger.add(edges * (9 + 3), fp32=True)
    return ledger


def _checkpointed_peak(stages: list[_Stage], compute_bytes: int) -> int:
    """Backward reruns the parts last to first; while part k reruns, the outputs kept for the parts
    before it are alive, those of the parts after it are freed already."""
    peak = kept = 0
    for part, output in stages:
        peak = max(peak, kept + part.bytes(compute_bytes))
        kept += output.bytes(compute_bytes)
    return max(peak, kept)  # the end of the forward pass


def parameter_count(model_name: str, config) -> int:
    """Exact, from the model built on the meta device (nothing is allocated)."""
    from aniformer.models import build_model

    with torch.device("meta"):
        model = build_model(_config(model_name, config))
    return sum(p.numel() for p in model.parameters())


def _config(model_name: str, config):
    if isinstance(config, dict):
        from aniformer.models import model_config

        config = model_config(model_name, {k: v for k, v in config.items() if k != "name"})
    return config


def predict_step_memory(model_name: str, config, *, vertices: int | tuple[int, int], batch: int,
                        precision: str = "fp32", device: str = "cpu", workers: int = 1,
                        faces: int | None = None, prefetch_batches: int = 2,
                        allocator_kind: str | None = None, activation_checkpointing: bool = False) -> MemoryEstimate:
    """Predicted peak memory of one training step (Adam, `batch` windows per worker) on `device`.

    `config` is the model's config (dataclass or dict); its `window` is T. `device` is "cpu" or
    "cuda" (picks the process overhead, and the allocator factor unless `allocator_kind` names an
    ALLOCATOR_FACTOR key); `precision` the autocast dtype; `activation_checkpointing` as the
    model's switch of that name.
    """
    if precision not in PRECISION_BYTES:
        raise ValueError(f"precision must be one of {sorted(PRECISION_BYTES)}, got {precision!r}")
    kind = "cuda" if str(device).startswith("cuda") else "cpu"
    config = _config(model_name, config)
    V1, V2 = (vertices, vertices) if isinstance(vertices, int) else vertices
    params = parameter_count(model_name, config)
    activations, workspace = count_activations(model_name, config, batch, (V1, V2), precision, faces,
                                               activation_checkpointing)
    T = config.window
    F = faces if faces is not None else 2 * V2
    inputs = (1 + prefetch_batches) * batch * (4 * (2 * T * V1 * 3 + V2 * 3) + 8 * F * 3)
    if precision != "fp32":  # autocast caches a low-precision copy of every weight during the forward
        workspace += params * PRECISION_BYTES[precision]
    return MemoryEstimate(
        parameters=4 * params, gradients=4 * params, optimizer=8 * params,
        ddp_buckets=4 * params if workers > 1 else 0,
        activations=activations, workspace=workspace, inputs=inputs,
        allocator_factor=ALLOCATOR_FACTOR[allocator_kind or allocator(kind)], overhead=int(PROCESS_OVERHEAD_GB[kind] * GiB),
    )
