"""Training checkpoints: one file, written atomically, loadable with `torch.load(weights_only=True)`.

Contract: {"config", "model", "optimizer", "scheduler", "epoch", "step", "rng"}. `config` is the
whole run config as plain data (the model section names the model and its hyper-parameters), so a
checkpoint alone rebuilds its model. Only tensors and plain Python values are stored: no pickled
classes, so loading never executes code from the file.

Loading checks before it allocates: the model a checkpoint's config describes is first built on
PyTorch's "meta" device (shapes only, nothing allocated), its parameter count is bounded
(`MAX_PARAMETERS`), and its tensors must be exactly those of the state dict in the file, so a small
file whose config asks for `channels: [65536, 65536]` is refused before any weight is made. Weights
that are NaN or infinite are refused too: a diverged model's output is never scored or written.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from importlib.resources import files
from pathlib import Path

import torch
from torch import nn

from aniformer.errors import UserError
from aniformer.io.files import atomic_path
from aniformer.models import build_model, model_config

#: The model shipped with the project (docs/model_card.md), what ``--checkpoint pretrained`` names: package data of
#: `aniformer` (pyproject.toml), so an installed package has it too. pip installs packages as plain files, so it
#: is a real path (`Path` fails at import otherwise, not at the first load).
PRETRAINED = Path(files("aniformer") / "weights" / "aniformer.pt")
KEYS = ("config", "model", "optimizer", "scheduler", "epoch", "step", "rng")
FILENAME = "checkpoint.pt"
# Far above any model of this project (the shipped one has 46,629 parameters, configs/paper.yaml 12 M): a config
# beyond it is refused before the model is built, whatever the file holds (4 GiB of fp32 weights).
MAX_PARAMETERS = 2**30


def resolve_pretrained(reference: str) -> str:
    """A job's ``--checkpoint``: ``pretrained`` is the shipped model, anything else as given."""
    return str(PRETRAINED) if reference == "pretrained" else reference


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
    config = state["config"]
    if not isinstance(config, Mapping):
        raise UserError(f"{path}: the checkpoint's config is a {type(config).__name__}, not a mapping")
    if not isinstance(config.get("model", {}), Mapping):
        raise UserError(f"{path}: the checkpoint's model config is a {type(config['model']).__name__}, not a mapping")
    return state


def _planned_tensors(path: Path, name: str, section: dict) -> dict[str, torch.Size]:
    """The state dict's shapes of the model `section` describes, built on the meta device (nothing is
    allocated, whatever the widths)."""
    try:
        with torch.device("meta"):
            model = build_model(model_config(name, section))
    except (ValueError, TypeError, RuntimeError) as e:
        raise UserError(f"{path}: checkpoint's model config is invalid ({' '.join(str(e).split())[:300]})") from None
    return {key: tensor.shape for key, tensor in model.state_dict().items()}


def check_weights(path: str | os.PathLike, name: str, section: dict, weights) -> None:
    """Refuse, before the model is built, a config whose model exceeds `MAX_PARAMETERS` or whose
    tensors are not exactly the state dict's (names and shapes), and weights that are not finite."""
    planned = _planned_tensors(Path(path), name, section)
    count = sum(shape.numel() for shape in planned.values())
    if count > MAX_PARAMETERS:
        raise UserError(f"{path}: the checkpoint's config describes a model of {count:,} parameters "
                        f"({4 * count / 2**30:,.1f} GiB); refusing more than {MAX_PARAMETERS:,}")
    if not isinstance(weights, Mapping) or not all(isinstance(t, torch.Tensor) for t in weights.values()):
        raise UserError(f"{path}: the checkpoint's model weights are not a state dict of tensors")
    held = sum(t.numel() for t in weights.values())
    missing = sorted(set(planned) - set(weights))
    unexpected = sorted(set(weights) - set(planned))
    wrong = [k for k in planned if k in weights and weights[k].shape != planned[k]]
    if missing or unexpected or wrong:
        first = (f"{wrong[0]} is {tuple(weights[wrong[0]].shape)}, the config says {tuple(planned[wrong[0]])}" if wrong
                 else f"missing {', '.join(missing[:3])}" if missing else f"unexpected {', '.join(unexpected[:3])}")
        raise UserError(f"{path}: checkpoint does not match its model config: the config describes {count:,} "
                        f"parameters, the file holds {held:,} ({first})")
    for key, tensor in weights.items():
        if tensor.is_floating_point() and not torch.isfinite(tensor).all():
            bad = int((~torch.isfinite(tensor)).sum())
            raise UserError(f"{path}: the checkpoint's weights are not finite ({bad:,} NaN or infinite values "
                            f"in {key}): a diverged run?")


def model_from_checkpoint(path: str | os.PathLike) -> tuple[nn.Module, dict]:
    """Rebuild the model a checkpoint was trained with and load its weights; returns (model, state)."""
    state = load_checkpoint(path)
    section = dict(state["config"].get("model", {}))
    name = section.pop("name", "aniformer")
    check_weights(path, name, section, state["model"])
    try:
        model = build_model(model_config(name, section))
        model.load_state_dict(state["model"])
    except (ValueError, TypeError, RuntimeError) as e:
        detail = " ".join(str(e).split())  # load_state_dict names the mismatched tensors on later lines
        raise UserError(f"{path}: checkpoint does not match its model config ({detail[:300]})") from None
    return model.eval(), state
