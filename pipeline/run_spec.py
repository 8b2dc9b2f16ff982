"""A run's config, validated before anything starts: `RunSpec` (the data, model, loss and train sections)
and `TrainConfig` (optimisation and execution), with the precision a device trains in.

Every job builds its `RunSpec` from the loaded YAML first, so a bad config is one line before Ray starts;
`RunSpec.to_dict()` is what checkpoints and MLflow record, and `RunSpec.from_config` reads it back.
"""

from __future__ import annotations

from dataclasses import dataclass

from aniformer.config import Section, from_dict
from aniformer.errors import UserError
from aniformer.losses import LossConfig
from aniformer.model import ATTENTION_KERNELS
from aniformer.models import MODELS, ModelConfig
from pipeline.data import DataConfig, data_config

PRECISIONS = ("auto", "fp32", "bf16", "fp16")
COMPILE_MODES = ("none", "default", "reduce-overhead", "max-autotune")  # torch.compile's modes; none = eager
EVAL_SPLITS = ("seen", "unseen")


@dataclass(frozen=True)
class TrainConfig(Section):
    """Optimisation and execution; defaults are the paper's (Adam 5e-5, MultiStep 80/120/160 x0.1)."""

    epochs: int = 200
    batch_size: int = 2
    grad_accumulation: int = 1  # optimiser step every k batches: effective batch k * batch_size * workers
    lr: float = 5e-5
    milestones: tuple[int, ...] = (80, 120, 160)
    lr_decay: float = 0.1
    seed: int = 0
    workers: int = 1
    cpus_per_worker: float = 1.0
    use_gpu: bool = False
    placement_strategy: str = "PACK"  # SPREAD puts the workers on different nodes
    precision: str = "auto"  # auto: bf16 on GPUs that have it, fp16 + GradScaler on older (V100), fp32 on CPU
    compile: str = "none"  # torch.compile mode for the training forward/backward (reduce-overhead: CUDA graphs)
    activation_checkpointing: bool = False  # model parts keep only their inputs, rerun in backward (huge V)
    attention_kernels: tuple[str, ...] = ()  # SDPA kernels allowed, by preference (e.g. cudnn, flash, efficient)
    max_failures: int = 2
    keep_checkpoints: int = 2
    render_every: int = 5

    def __post_init__(self):
        super().__post_init__()
        for name in ("epochs", "batch_size", "grad_accumulation", "workers", "keep_checkpoints", "render_every"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.lr <= 0 or self.cpus_per_worker <= 0:
            raise ValueError("lr and cpus_per_worker must be > 0")
        if self.placement_strategy not in ("PACK", "SPREAD", "STRICT_PACK", "STRICT_SPREAD"):
            raise ValueError(f"placement_strategy must be PACK, SPREAD, STRICT_PACK or STRICT_SPREAD, "
                             f"got {self.placement_strategy!r}")
        if self.precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {PRECISIONS}, got {self.precision!r}")
        if self.compile not in COMPILE_MODES:
            raise ValueError(f"compile must be one of {COMPILE_MODES}, got {self.compile!r}")
        unknown = sorted(set(self.attention_kernels) - set(ATTENTION_KERNELS))
        if unknown:
            raise ValueError(f"attention_kernels: unknown {unknown}; choose from {sorted(ATTENTION_KERNELS)}")


@dataclass(frozen=True)
class RunSpec:
    """A validated run config: every section parsed, so bad input fails before Ray starts."""

    data: DataConfig
    model_name: str
    model: ModelConfig
    loss: LossConfig
    train: TrainConfig

    @classmethod
    def from_config(cls, config: dict) -> RunSpec:
        unknown = sorted(set(config) - {"data", "model", "loss", "train"})
        if unknown:
            raise UserError(f"unknown config section(s): {', '.join(unknown)} (known: data, model, loss, train)")
        section = dict(config.get("model") or {})
        name = section.pop("name", "aniformer")
        if name not in MODELS:
            raise UserError(f"[model] unknown name {name!r}; choose one of {sorted(MODELS)}")
        data = data_config(config)
        # T is set once, in data.window; a model section that names it (a checkpoint's does) must agree.
        if section.setdefault("window", data.window) != data.window:
            raise UserError(f"model.window={section['window']} differs from data.window={data.window}: "
                            "set the window once, in data.window")
        model = from_dict(MODELS[name][1], section, "model")
        return cls(data, name, model, from_dict(LossConfig, config.get("loss"), "loss"),
                   from_dict(TrainConfig, config.get("train"), "train"))

    def to_dict(self) -> dict:
        return {"data": self.data.to_dict(), "model": {"name": self.model_name, **self.model.to_dict()},
                "loss": self.loss.to_dict(), "train": self.train.to_dict()}


def resolve_precision(requested: str, device_type: str, bf16_supported: bool) -> str:
    """``auto``: bf16 on GPUs that have it, fp16 (with a GradScaler) on older ones (V100), fp32 on CPU."""
    if requested != "auto":
        return requested
    if device_type != "cuda":
        return "fp32"
    return "bf16" if bf16_supported else "fp16"
