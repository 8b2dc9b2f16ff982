"""The sweeps' memory gate: the batch a trial runs at, decided from `aniformer.memory`'s predicted peak before
the trial builds anything (docs/sweeps.md). The prediction is the model's; the policy (halve the batch, keep the
effective batch by accumulation, skip what cannot fit) is the sweep's."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from aniformer.memory import predict_step_memory
from aniformer.models import ModelConfig
from pipeline.run_spec import resolve_precision
from pipeline.sweep_config import SweepConfig


@dataclass(frozen=True)
class BatchPlan:
    """The memory gate's decision for one config: run as asked, with a smaller batch, or not at all."""

    status: str  # "ok" | "adjusted_memory" | "skipped_memory"
    batch_size: int  # per-worker micro-batch to run
    grad_accumulation: int  # optimiser step every k micro-batches (keeps the effective batch)
    requested_gb: float  # predicted per-worker peak at the requested batch
    predicted_gb: float  # predicted per-worker peak of what will run (of batch 1 when skipped)
    limit_gb: float

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def plan_batch(config: ModelConfig, *, vertices, batch: int, grad_accumulation: int = 1,
               limit_gb: float | None, **kwargs) -> BatchPlan:
    """Halve the batch (doubling gradient accumulation) until the predicted peak fits `limit_gb`.

    "ok" if the requested batch fits (or there is no limit), "adjusted_memory" if a smaller one
    does, "skipped_memory" if not even batch 1 does. Nothing is allocated to find out.
    """
    def predict(b: int) -> float:
        return predict_step_memory(config, vertices=vertices, batch=b, **kwargs).total_gb

    requested = predict(batch)
    if limit_gb is None or requested <= limit_gb:
        return BatchPlan("ok", batch, grad_accumulation, requested, requested, limit_gb or math.inf)
    b, predicted = batch, requested
    while b > 1:
        b = max(1, b // 2)
        predicted = predict(b)
        if predicted <= limit_gb:
            return BatchPlan("adjusted_memory", b, grad_accumulation * math.ceil(batch / b), requested,
                             predicted, limit_gb)
    return BatchPlan("skipped_memory", 1, grad_accumulation * batch, requested, predicted, limit_gb)  # of batch 1


def gate(spec, vertices: int, faces: int | None, sweep: SweepConfig):
    """The memory decision (`BatchPlan`) for one trial's RunSpec."""
    cfg = spec.train
    device = "cuda" if cfg.use_gpu else "cpu"
    # The driver cannot see the workers' GPUs; bf16 and fp16 take the same memory.
    precision = resolve_precision(cfg.precision, device, bf16_supported=True)
    plan = plan_batch(spec.model, vertices=vertices, batch=cfg.batch_size, grad_accumulation=cfg.grad_accumulation,
                      limit_gb=sweep.memory_limit_gb, precision=precision, device=device, workers=cfg.workers,
                      faces=faces, activation_checkpointing=cfg.activation_checkpointing)
    if plan.status == "adjusted_memory" and plan.grad_accumulation > sweep.max_grad_accumulation:
        plan = dataclasses.replace(plan, status="skipped_memory")
    return plan
