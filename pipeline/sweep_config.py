"""The `sweep:` section of a sweep config (`SweepConfig`), the search space it spans, and how one
sampled point becomes a trial's run config (`apply_params`)."""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np
from ray import tune

from aniformer.config import Section, from_dict
from aniformer.errors import UserError

SEARCHES = ("optuna", "random")
# tune parameter -> the config keys it sets
PARAMS = {"rec": ("loss.rec",), "motion": ("loss.motion",), "appearance": ("loss.appearance",),
          "window": ("data.window",), "lr": ("train.lr",), "batch_size": ("train.batch_size",)}
def _bounds(name: str, value, kind=float) -> tuple | None:
    if value is None:
        return None
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        raise ValueError(f"{name} must be [low, high], got {value!r}")
    low, high = (kind(v) for v in value)
    if not 0 < low <= high:
        raise ValueError(f"{name} must satisfy 0 < low <= high, got {value!r}")
    return low, high


@dataclass(frozen=True)
class SweepConfig(Section):
    """The `sweep:` section of a sweep config (bounds are [low, high], inclusive; log-uniform for floats)."""

    num_samples: int = 8
    max_concurrent: int = 2
    search: str = "optuna"  # optuna (TPE) | random
    seed: int = 0
    metric: str = "pmd_unseen"  # minimised; reported every epoch by train_func
    rec: tuple = (0.1, 10.0)
    motion: tuple = (1e-5, 1e-2)
    appearance: tuple = (1e-5, 1e-2)
    window: tuple = (2, 8)
    lr: tuple | None = None  # e.g. [1e-5, 1e-3]
    batch_size: tuple | None = None  # choices, e.g. [1, 2, 4]
    memory_limit_gb: float | None = None  # per training worker; none = no gate
    max_grad_accumulation: int = 16  # an adjustment needing more is a skip
    grace_period: int = 1  # ASHA: epochs before a trial may be stopped
    reduction_factor: int = 2
    trial_cpus: float = 0.05  # the trial driver actor (> 0; the TorchTrainer's workers take train.cpus_per_worker)
    points: tuple = ()  # configs tried first (dicts of searched parameters; missing ones: mid-range)

    def __post_init__(self):
        super().__post_init__()
        for name in ("rec", "motion", "appearance", "lr"):
            object.__setattr__(self, name, _bounds(name, getattr(self, name)))
        object.__setattr__(self, "window", _bounds("window", self.window, int))
        if self.batch_size is not None:
            choices = tuple(int(b) for b in self.batch_size)
            if not choices or min(choices) < 1:
                raise ValueError(f"batch_size must list positive batch sizes, got {self.batch_size!r}")
            object.__setattr__(self, "batch_size", choices)
        points = tuple(dict(p) for p in (self.points or ()))
        for point in points:
            unknown = sorted(set(point) - set(PARAMS))
            if unknown:
                raise ValueError(f"points: unknown parameter(s) {unknown} (known: {sorted(PARAMS)})")
        object.__setattr__(self, "points", points)
        if self.search not in SEARCHES:
            raise ValueError(f"search must be one of {SEARCHES}, got {self.search!r}")
        for name in ("num_samples", "max_concurrent", "max_grad_accumulation", "grace_period"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.reduction_factor < 2:
            raise ValueError(f"reduction_factor must be >= 2, got {self.reduction_factor}")
        if self.memory_limit_gb is not None and self.memory_limit_gb <= 0:
            raise ValueError(f"memory_limit_gb must be > 0, got {self.memory_limit_gb}")
        if not self.trial_cpus > 0:
            raise ValueError(f"trial_cpus must be > 0 (Tune needs a resource request), got {self.trial_cpus}")


def split_config(config: dict) -> tuple[dict, SweepConfig]:
    """A loaded sweep config -> (the run config for RunSpec, the parsed `sweep:` section)."""
    config = dict(config)
    sweep = from_dict(SweepConfig, config.pop("sweep", None), "sweep")
    return config, sweep


def search_space(sweep: SweepConfig) -> dict:
    space = {name: tune.loguniform(*getattr(sweep, name)) for name in ("rec", "motion", "appearance")}
    space["window"] = tune.randint(sweep.window[0], sweep.window[1] + 1)  # upper bound exclusive
    if sweep.lr:
        space["lr"] = tune.loguniform(*sweep.lr)
    if sweep.batch_size:
        space["batch_size"] = tune.choice(list(sweep.batch_size))
    return space


def complete_points(sweep: SweepConfig, base_batch: int) -> list[dict]:
    """`sweep.points` with every searched parameter set (Optuna needs whole points): missing ones at
    the middle of their range (geometric for log-uniform ones), the config's batch if it is a choice."""
    space = search_space(sweep)
    middle = {name: math.sqrt(getattr(sweep, name)[0] * getattr(sweep, name)[1])
              for name in ("rec", "motion", "appearance", "lr") if getattr(sweep, name)}
    middle["window"] = (sweep.window[0] + sweep.window[1]) // 2
    if sweep.batch_size:
        middle["batch_size"] = base_batch if base_batch in sweep.batch_size else sweep.batch_size[0]
    points = []
    for point in sweep.points:
        outside = sorted(set(point) - set(space))
        if outside:
            raise UserError(f"sweep.points: {outside} not searched (set sweep.{outside[0]} to search it)")
        if "batch_size" in point and point["batch_size"] not in sweep.batch_size:
            raise UserError(f"sweep.points: batch_size {point['batch_size']} is not one of sweep.batch_size")
        points.append({name: point.get(name, middle[name]) for name in space})
    return points


def apply_params(config: dict, params: dict) -> dict:
    """The run config of one trial: `config` with the sampled parameters set (a deep copy)."""
    config = copy.deepcopy(config)
    for name, value in params.items():
        if name not in PARAMS:
            continue
        if isinstance(value, np.generic):
            value = value.item()
        for key in PARAMS[name]:
            section, leaf = key.split(".")
            config.setdefault(section, {})[leaf] = value
    return config
