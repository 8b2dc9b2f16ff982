"""Training checkpoints: one file, written atomically, loadable with `torch.load(weights_only=True)`.

Contract: {"config", "model", "optimizer", "scheduler", "epoch", "step", "rng"}. `config` is the
whole run config as plain data (the model section names the model and its hyper-parameters), so a
checkpoint alone rebuilds its model. Only tensors and plain Python values are stored: no pickled
classes, so loading never executes code from the file.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
from torch import nn

from aniformer.baselines import build_model
from aniformer.cli import UserError, atomic_path

#: The model shipped with the project (docs/model_card.md), what ``--checkpoint pretrained`` names.
PRETRAINED = Path(__file__).resolve().parents[1] / "models" / "aniformer.pt"
KEYS = ("config", "model", "optimizer", "scheduler", "epoch", "step", "rng")
FILENAME = "checkpoint.pt"


def checkpoint_spec(spec: str) -> str:
    """A job's ``--checkpoint``: ``pretrained`` is the shipped model, anything else as given."""
    return str(PRETRAINED) if spec == "pretrained" else spec


def unwrap(model: nn.Module) -> nn.Module:
    """The model inside torch.compile's and DistributedDataParallel's wrappers (compile wraps DDP)."""
    model = getattr(model, "_orig_mod", model)
    return getattr(model, "module", model)


def save_checkpoint(path: str | os.PathLike, *, config: dict, model: nn.Module, optimizer, scheduler,
                    epoch: int, step: int) -> Path:
    state = {
        "config": config,
        "model": unwrap(model).state_dict(),
        "optimizer": optimizer.state_dict(),
        "scheduler": scheduler.state_dict(),
        "epoch": epoch,
        "step": step,
        "rng": torch.get_rng_state(),
    }
    with atomic_path(path) as tmp:
        torch.save(state, tmp)
    return Path(path)


def load_checkpoint(path: str | os.PathLike) -> dict:
    """Read a checkpoint file (or a directory holding `checkpoint.pt`); `UserError` if it is not one."""
    path = Path(path)
    if path.is_dir():
        path = path / FILENAME
    if not path.is_file():
        raise UserError(f"checkpoint not found: {path}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # garbage bytes, truncated file, or a pickle that is not plain data
        raise UserError(f"{path}: not a readable checkpoint ({type(e).__name__})") from None
    missing = [k for k in KEYS if not isinstance(state, dict) or k not in state]
    if missing:
        raise UserError(f"{path}: not an AniFormer checkpoint (missing {', '.join(missing)})")
    return state


def model_from_checkpoint(path: str | os.PathLike) -> tuple[nn.Module, dict]:
    """Rebuild the model a checkpoint was trained with and load its weights; returns (model, state)."""
    state = load_checkpoint(path)
    section = dict(state["config"].get("model", {}))
    name = section.pop("name", "aniformer")
    try:
        model = build_model(name, section)
        model.load_state_dict(state["model"])
    except (ValueError, TypeError, RuntimeError) as e:
        detail = " ".join(str(e).split())  # load_state_dict names the mismatched tensors on later lines
        raise UserError(f"{path}: checkpoint does not match its model config ({detail[:300]})") from None
    return model.eval(), state
