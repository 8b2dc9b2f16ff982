"""Peak memory of one training step, counted from the model itself before anything is allocated.

Used by the sweeps (`pipeline/tune.py`) to know whether a trial fits a worker *before* it starts:
a trial predicted over the per-worker limit gets a smaller batch with gradient accumulation, or is
skipped. Pure: torch only.

The count runs the real training step -- the model built from its config, its forward under autocast,
the loss of eq. 6 (`aniformer.losses`), backward -- on fake tensors: tensors with shapes and dtypes but
no data (`FakeTensorMode`, meta storage underneath), so nothing is allocated and the count is exact at
any size. Fake tensors on the "cpu" device, not plain meta ones: `torch.autocast` casts only tensors of
its device. A dispatch mode (`_LiveBytes`) sees every storage the step's ops create and when it is freed;
nothing in this module knows the layers, so the count follows the model when it changes. What a training
step holds at its peak::

    held         parameters + Adam's two moments (2x)  [+ 1x DDP buckets, >1 worker]
    activations  what the step's ops created that is alive when backward starts: the tensors autograd
                 saves for it, autocast's low-precision weight copies among them; with activation
                 checkpointing, the checkpointed parts' inputs and what is saved outside them
    workspace    what backward holds above that at its peak: gradient buffers, the parameters'
                 gradients made by then (all of them at its end), with activation checkpointing the
                 part being rerun
    inputs       the batch (driving, target, ground truth, faces) and the prefetched ones
    overhead     what the process holds before the step: interpreter + torch + Ray on CPU,
                 the CUDA context and allocator slack on a GPU

Attention saves its output and log-sum-exp (`F.scaled_dot_product_attention`'s fused kernels, CPU and GPU
alike): memory linear in V, no V x V map. Not counted: Adam's own transients (about 1x parameters on
CUDA, where it steps all of them at once; one parameter's size on CPU) and, under gradient accumulation,
the gradients that the later micro-batches hold throughout (up to 1x parameters more). Under
`torch.compile` a step holds less than eagerly, so the eager count is an upper bound for it.

Calibration. The fake count equals the same count of a real CPU step, byte for byte (tests/test_memory.py).
On CPU, peak RSS is larger than the peak of live tensors: glibc's malloc raises its mmap threshold
dynamically, after which freed activation buffers stay in the heap, fragmented. `ALLOCATOR_FACTOR["cpu"]`
(fitted by bench/memory_calibration.py, error in docs/benchmarks.md) scales the dynamic part for that; with
`MALLOC_MMAP_THRESHOLD_` set, RSS follows the live tensors and the factor is 1. On CUDA,
`torch.cuda.max_memory_allocated` counts live tensors only: on an H100 its dynamic part was 1.00-1.03x this
count (9 configs, bf16/fp16/fp32, checkpointed or not; Adam's transients the most of the difference); the
factor there is headroom for that and for what the caching allocator reserves beyond it.
"""

from __future__ import annotations

import dataclasses
import os
import weakref
from dataclasses import dataclass

import torch
from torch._subclasses.fake_tensor import FakeTensorMode
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_leaves

from aniformer.losses import LossConfig, loss_terms
from aniformer.models import ModelConfig, build_model

GiB = 2**30

# The autocast dtype of each training precision (None: no autocast).
AUTOCAST = {"fp32": None, "bf16": torch.bfloat16, "fp16": torch.float16}

# Peak memory over the live-tensor peak of the dynamic part (activations + workspace + inputs).
# "cpu": peak RSS under glibc's default malloc, which raises its mmap threshold as large buffers are
#   freed, after which freed activation buffers stay resident (fragmented heap): RSS grows over the
#   first ~8 steps to 1.5-1.8x the live peak (bench/memory_calibration.py, docs/benchmarks.md).
# "cpu-mmap": the same with MALLOC_MMAP_THRESHOLD_ set (large buffers mmapped and returned on free):
#   peak RSS is the live peak, within +-5%.
# "cuda": torch.cuda.max_memory_allocated counts live tensors; 1.1 over-predicts it by 6-10%
#   (docs/benchmarks.md): headroom kept for the caching allocator's reserved-but-unallocated blocks
#   (max_memory_reserved, printed by the calibration).
ALLOCATOR_FACTOR = {"cpu": 1.7, "cpu-mmap": 1.0, "cuda": 1.1}


def allocator(device: str) -> str:
    """The ALLOCATOR_FACTOR key for `device` in this process's environment."""
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
        """What lives from one step to the next (the gradients from backward to the optimizer step)."""
        return self.parameters + self.gradients + self.optimizer + self.ddp_buckets

    @property
    def dynamic(self) -> int:
        """Activations + workspace + inputs, scaled by the allocator factor."""
        return int(self.allocator_factor * (self.activations + self.workspace + self.inputs))

    @property
    def step(self) -> int:
        """What one training step adds to a process: what the calibration measures. The gradients are
        made by backward, inside the dynamic part (all of them alive at its end)."""
        return self.parameters + self.optimizer + self.ddp_buckets + self.dynamic

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


class _LiveBytes(TorchDispatchMode):
    """The bytes of the storages that ops create under this mode, alive now and at most (`peak`).

    Views and in-place results share a storage of the op's inputs and add nothing; tensors made before
    the mode (parameters, the batch) are not counted. Real or fake tensors alike.
    """

    def __init__(self):
        super().__init__()
        self.live: dict[int, int] = {}  # StorageImpl address -> bytes, of the storages alive
        self.alive = self.peak = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        inputs = {t.untyped_storage()._cdata for t in tree_leaves((args, kwargs)) if isinstance(t, torch.Tensor)}
        for t in tree_leaves(out):
            if isinstance(t, torch.Tensor):
                storage = t.untyped_storage()
                key = storage._cdata  # the StorageImpl's address: fake and meta storages have no data pointer
                if key not in inputs and key not in self.live:
                    self.live[key] = storage.nbytes()
                    self.alive += storage.nbytes()
                    weakref.finalize(storage, self._freed, key)
        self.peak = max(self.peak, self.alive)
        return out

    def _freed(self, key: int) -> None:
        self.alive -= self.live.pop(key)


def step_memory(model: torch.nn.Module, driving: torch.Tensor, target: torch.Tensor, truth: torch.Tensor,
                faces: torch.Tensor, precision: str = "fp32") -> tuple[int, int]:
    """(activations, workspace) in bytes of one training step of `model` on this batch, as pipeline/train.py
    runs it: forward under autocast, the loss of eq. 6 in fp32 outside it, backward (module docstring).
    Real or fake tensors alike; the batch and the parameters are not counted."""
    dtype = AUTOCAST[precision]
    frames = model.config.output_frames()
    model.zero_grad(set_to_none=True)  # as train.py leaves it: this step's backward creates the gradients
    counted = _LiveBytes()
    with torch.enable_grad(), counted:
        with torch.autocast(driving.device.type, dtype=dtype, enabled=dtype is not None):
            pred = model(driving, target, faces)
        terms = loss_terms(pred.float(), truth[:, frames], driving[:, frames], target, faces, LossConfig())
        activations = counted.alive
        terms["total"].backward()
    return activations, counted.peak - activations


def _fake_step(config: ModelConfig, batch: int, vertices: int | tuple[int, int], faces: int | None,
               precision: str, activation_checkpointing: bool) -> tuple[int, int, int, int]:
    """(parameters, activation bytes, workspace bytes, batch bytes) of one training step at this size, on fake tensors."""
    V1, V2 = (vertices, vertices) if isinstance(vertices, int) else vertices
    F, T = faces if faces is not None else 2 * V2, config.window  # a closed mesh has 2 V faces
    with torch.device("meta"):  # meta first: initialisers such as trunc_normal_ read values, fake tensors have none
        model = build_model(config)
    params = sum(p.numel() for p in model.parameters())
    if hasattr(model, "prior"):
        # The transfer is solved by scipy, which needs numbers fake tensors lack. Its prior comes from detached inputs,
        # outside autograd, and saves nothing: zeros of its shape count the same (tests/test_memory.py).
        model.prior = lambda driving, target, faces: torch.zeros_like(driving)
    with FakeTensorMode(allow_non_fake_inputs=True):  # non-fake: to_empty reads the meta parameters
        model.to_empty(device="cpu")
        model.activation_checkpointing = activation_checkpointing
        driving, target, truth = torch.empty(batch, T, V1, 3), torch.empty(batch, V2, 3), torch.empty(batch, T, V2, 3)
        target_faces = torch.zeros(batch, F, 3, dtype=torch.int64)  # one (F, 3) per sample, as train.py's batches
        activations, workspace = step_memory(model, driving, target, truth, target_faces, precision)
    return params, activations, workspace, sum(t.nbytes for t in (driving, target, truth, target_faces))


def count_activations(config: ModelConfig, batch: int, vertices: int | tuple[int, int], precision: str = "fp32",
                      faces: int | None = None, activation_checkpointing: bool = False) -> tuple[int, int]:
    """(activation bytes, workspace bytes) of one training step of `batch` windows (module docstring).

    `vertices` = V or (V1 driving, V2 target); `faces` = triangles of the target (default 2*V2, a closed mesh).
    """
    _, activations, workspace, _ = _fake_step(config, batch, vertices, faces, precision, activation_checkpointing)
    return activations, workspace


def parameter_count(config: ModelConfig) -> int:
    """Exact, from the model built on the meta device (nothing is allocated)."""
    with torch.device("meta"):
        model = build_model(config)
    return sum(p.numel() for p in model.parameters())


def predict_step_memory(config: ModelConfig, *, vertices: int | tuple[int, int], batch: int,
                        precision: str = "fp32", device: str = "cpu", workers: int = 1,
                        faces: int | None = None, prefetch_batches: int = 2,
                        allocator_kind: str | None = None, activation_checkpointing: bool = False) -> MemoryEstimate:
    """Predicted peak memory of one training step (Adam, `batch` windows per worker) on `device`.

    `config` is the model's typed config (`aniformer.models.model_config`); its `window` is T. `vertices`
    is V, or (V1 driving, V2 target). `device` is "cpu" or "cuda" (picks the process overhead, and the
    allocator factor unless `allocator_kind` names an ALLOCATOR_FACTOR key); `precision` the autocast
    dtype; `activation_checkpointing` as the model's switch of that name.
    """
    if precision not in AUTOCAST:
        raise ValueError(f"precision must be one of {sorted(AUTOCAST)}, got {precision!r}")
    kind = "cuda" if str(device).startswith("cuda") else "cpu"
    params, activations, workspace, batch_bytes = _fake_step(config, batch, vertices, faces, precision,
                                                             activation_checkpointing)
    return MemoryEstimate(
        parameters=4 * params, gradients=4 * params, optimizer=8 * params,
        ddp_buckets=4 * params if workers > 1 else 0,
        activations=activations, workspace=workspace, inputs=(1 + prefetch_batches) * batch_bytes,
        allocator_factor=ALLOCATOR_FACTOR[allocator_kind or allocator(kind)], overhead=int(PROCESS_OVERHEAD_GB[kind] * GiB),
    )
