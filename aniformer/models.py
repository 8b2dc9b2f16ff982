"""Every model a config can name (`MODELS`, `build_model`): AniFormer (aniformer/model.py) and the baselines of
the paper's Table 1/2, all with the AniFormer interface `model(driving (B, T, V1, 3), target (B, V2, 3)) -> (B, T, V2, 3)`.

- NPT: Wang et al., "Neural Pose Transfer by Spatially Adaptive Instance Normalization", CVPR 2020.
  PointNet pose encoder; its per-vertex features concatenated with the identity (target)
  coordinates; SPAdaIN residual decoder; applied frame by frame, as the paper compares it.
- Regression-head transformer (Table 1 "head"): `AniFormerConfig(head="regression")`, one mesh
  per window; built through `build_model` like the others.
- Copy-driver: the bounding-box-centred driving frames themselves; the floor any model must beat,
  defined only where driver and target share a topology.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import torch
from einops import rearrange
from torch import nn

from aniformer.config import Section
from aniformer.geometry import center_bbox
from aniformer.model import AniFormer, AniFormerConfig, FeatureExtractor, SPAdaINResBlock, run_block


@dataclass(frozen=True)
class NPTConfig(Section):
    """NPT's published widths: encoder 64-128-1024, decoder 1027-513-256 (1027 = 1024 + xyz)."""

    extractor_channels: tuple[int, ...] = (64, 128, 1024)
    channels: tuple[int, ...] = (1027, 513, 256)
    window: int = 3  # frames per sample; NPT treats them independently

    def __post_init__(self):
        super().__post_init__()
        if not self.channels or not self.extractor_channels:
            raise ValueError("channels and extractor_channels must not be empty")

    def output_frames(self) -> slice:
        return slice(None)


class NPT(nn.Module):
    def __init__(self, config: NPTConfig = NPTConfig()):
        super().__init__()
        self.config = config
        self.extractor = FeatureExtractor(config.extractor_channels)
        widths = (config.extractor_channels[-1] + 3, *config.channels)
        self.projections = nn.ModuleList(nn.Linear(a, b) for a, b in zip(widths[:-1], widths[1:]))
        self.blocks = nn.ModuleList(SPAdaINResBlock(c) for c in config.channels)
        self.to_xyz = nn.Linear(config.channels[-1], 3)
        self.activation_checkpointing = False  # as AniFormer's: keep the extractor's and each block's input

    def forward(self, driving: torch.Tensor, target: torch.Tensor, faces: torch.Tensor | None = None) -> torch.Tensor:
        """`faces` is unused: the same call as AniFormer's."""
        B, T, V1, _ = driving.shape
        V2 = target.shape[1]
        frames = rearrange(driving, "b t v c -> (b t) 1 v c")  # frame by frame: frames become samples
        identity = target.repeat_interleave(T, dim=0)
        pose = run_block(self.extractor, self.activation_checkpointing, frames)
        if V1 != V2:  # no vertex correspondence: broadcast the pooled pose code
            pose = pose.amax(dim=2, keepdim=True).expand(-1, -1, V2, -1)
        x = torch.cat([pose, identity.unsqueeze(1)], dim=-1)
        for projection, block in zip(self.projections, self.blocks):
            x = run_block(block, self.activation_checkpointing, projection(x), identity)
        return rearrange(2 * torch.tanh(self.to_xyz(x)), "(b t) 1 v c -> b t v c", b=B)


def copy_driver(driving: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """The driving frames, bounding-box centred; needs the target's topology (same vertex count)."""
    if driving.shape[2] != target.shape[1]:
        raise ValueError(f"copy-driver needs equal vertex counts, got driver {driving.shape[2]} "
                         f"and target {target.shape[1]}")
    return center_bbox(driving)


MODELS = {"aniformer": (AniFormer, AniFormerConfig), "npt": (NPT, NPTConfig)}
ModelConfig = AniFormerConfig | NPTConfig


def model_config(name: str, section: Mapping) -> ModelConfig:
    """The typed config of registry model ``name`` from its mapping (a checkpoint's or MLflow's, without "name")."""
    if name not in MODELS:
        raise ValueError(f"unknown model {name!r}; choose one of {sorted(MODELS)}")
    return MODELS[name][1](**section)


def build_model(config: ModelConfig) -> nn.Module:
    """The model a typed config describes."""
    model_cls = next((model for model, kind in MODELS.values() if type(config) is kind), None)
    if model_cls is None:
        raise TypeError(f"not a model config: {type(config).__name__}")
    return model_cls(config)
