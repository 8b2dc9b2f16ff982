"""AniFormer: a transformer that animates a target mesh with the motion of a driving mesh sequence.

Haoyu Chen, Hao Tang, Nicu Sebe, Guoying Zhao. "AniFormer: Data-driven 3D Animation with
Transformer". BMVC 2021. Section 3 and supplementary Tables 3-6 give the network:

    feature extractor (Table 3)   PointNet-style per-vertex MLP 3 -> 64 -> 128 -> 1024,
                                  each InstanceNorm + ReLU, weights shared by all frames
    temporal embedding (eq. 1)    Z = {Z_1; ...; Z_T} + E_t
    4 encoder stages (Tables 4,6) at 1024, 512, 512, 256 channels, each
                                  1x1 conv -> attention A = softmax(q k^T) (eq. 2)
                                  -> Z' = gamma * A v + Z, gamma initialised to 0 (eq. 3)
                                  -> InsNorm residual block modulated by the target mesh
    InsNorm block (Table 5)       SPAdaIN: InstanceNorm(x) * w(target_xyz) + b(target_xyz)
    output (Table 6)              1x1 conv -> 3, 2 * tanh; one mesh per driving frame
                                  (the "regression constraints" of Sec. 3.2 supervise them all)

We follow the paper's text, not the accidents of its public code (see docs/model.md): standard
multi-head attention (scaled by 1/sqrt(d)) instead of single-head unscaled; InstanceNorm in the
extractor instead of LayerNorm(6890); and a per-frame temporal embedding `(T, C)` instead of a
per-vertex `(T, C, V)` one, so that V is free. Attention goes through
`F.scaled_dot_product_attention`, which never materialises the V x V matrix (flash /
memory-efficient kernels); 1x1 convolutions are `nn.Linear` over channels-last `(..., V, C)`
tensors, which is the layout those kernels want. `model.activation_checkpointing = True` keeps only
the inputs of the feature extractors and of each stage's attention and block for backward and reruns
them there (an execution switch for huge V, not part of the architecture: neither in the config nor
in checkpoints).

Switches beyond the paper (all in `AniFormerConfig`):
    attention="cross"       target-vertex queries attend to driving-vertex keys/values, so the
                            output is permutation-equivariant in the target and V1 != V2 is free
    temporal="attention"    each vertex additionally attends across the T frames
    head="regression"       the vanilla regression-head transformer of Table 1 (one mesh per window)
    output="residual"       the driver plus a predicted per-vertex correction (needs driver and
                            target on one topology, V1 == V2, in corresponding vertex order);
                            the correction layer starts at zero, so training starts from copy-driver
    output="transfer"       the same on top of the deformation transfer of the target into each
                            driving pose (aniformer/transfer.py: the target's edges turned by the
                            driver's per-vertex rotations); needs the faces: model(d, t, faces). The
                            result is bounding-box centred per frame, like the transfer itself
    pool_driving=True       the paper's max-pool variant for non-SMPL meshes: driving features are
                            max-pooled over vertices and broadcast to the target's vertices (used
                            automatically by attention="self" when V1 != V2)
"""

from __future__ import annotations

from contextlib import nullcontext
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from einops import rearrange
from torch import nn
from torch.nn.attention import SDPBackend, sdpa_kernel
from torch.utils.checkpoint import checkpoint

from aniformer.config import Section
from aniformer.geometry import center_bbox
from aniformer.transfer import deformation_transfer

ATTENTIONS = ("self", "cross")
TEMPORALS = ("embedding", "attention")
HEADS = ("constraints", "regression")
OUTPUTS = ("absolute", "residual", "transfer")
# The fused kernels of F.scaled_dot_product_attention; "math" materialises the V x V map.
ATTENTION_KERNELS = {"cudnn": SDPBackend.CUDNN_ATTENTION, "flash": SDPBackend.FLASH_ATTENTION,
                     "efficient": SDPBackend.EFFICIENT_ATTENTION, "math": SDPBackend.MATH}


@dataclass(frozen=True)
class AniFormerConfig(Section):
    """Hyper-parameters; the defaults are the paper's layer plan."""

    channels: tuple[int, ...] = (1024, 512, 512, 256)
    extractor_channels: tuple[int, ...] = (64, 128, 1024)
    heads: int | tuple[int, ...] = 8  # one count for every stage, or one per stage
    window: int = 3
    attention: str = "self"
    temporal: str = "embedding"
    head: str = "constraints"
    output: str = "absolute"
    pool_driving: bool = False

    def __post_init__(self):
        super().__post_init__()
        if self.attention not in ATTENTIONS:
            raise ValueError(f"attention must be one of {ATTENTIONS}, got {self.attention!r}")
        if self.temporal not in TEMPORALS:
            raise ValueError(f"temporal must be one of {TEMPORALS}, got {self.temporal!r}")
        if self.head not in HEADS:
            raise ValueError(f"head must be one of {HEADS}, got {self.head!r}")
        if self.output not in OUTPUTS:
            raise ValueError(f"output must be one of {OUTPUTS}, got {self.output!r}")
        if not self.channels or not self.extractor_channels:
            raise ValueError("channels and extractor_channels must not be empty")
        if self.window < 1:
            raise ValueError(f"window must be >= 1, got {self.window}")
        if not all(isinstance(h, int) for h in self.stage_heads()):
            raise ValueError(f"heads must be an integer or a list of integers, got {self.heads!r}")
        if isinstance(self.heads, tuple) and len(self.heads) != len(self.channels):
            raise ValueError(f"heads needs one count per stage ({len(self.channels)}), got {list(self.heads)}")
        if any(h < 1 or c % h for c, h in zip(self.channels, self.stage_heads())):
            raise ValueError(f"every stage's channel count must be divisible by its heads: channels "
                             f"{list(self.channels)}, heads {list(self.stage_heads())}")

    def stage_heads(self) -> tuple[int, ...]:
        """The attention heads of each encoder stage. The fused attention kernels run fastest at head
        dim 128 (docs/benchmarks.md): heads = channels / 128, e.g. (8, 4, 4, 2) for the paper's widths."""
        return self.heads if isinstance(self.heads, tuple) else (self.heads,) * len(self.channels)

    def output_frames(self) -> slice:
        """Which frames of a window the model predicts: all of them, or the centre one (regression head)."""
        if self.head == "regression":
            return slice(self.window // 2, self.window // 2 + 1)
        return slice(None)


def attention_kernels(names: tuple[str, ...] | list[str]):
    """A context in which attention may use only the named kernels, the first that fits preferred
    (torch's own order, flash before cuDNN, when `names` is empty). A GPU without a kernel named
    (cuDNN/flash below sm_80) falls through to the next: list "efficient" last for V100s."""
    if not names:
        return nullcontext()
    return sdpa_kernel([ATTENTION_KERNELS[n] for n in names], set_priority=True)


def run_block(block, checkpointed: bool, *args: torch.Tensor | None) -> torch.Tensor:
    """`block(*args)`; checkpointed: autograd keeps only the inputs and reruns the block in backward."""
    if checkpointed and torch.is_grad_enabled():
        return checkpoint(block, *args, use_reentrant=False)
    return block(*args)


def instance_norm(x: torch.Tensor, eps: float = 1e-5) -> torch.Tensor:
    """Normalise every channel over the vertices of its mesh: `(..., V, C)`; statistics in fp32."""
    xf = x.float()
    var, mean = torch.var_mean(xf, dim=-2, unbiased=False, keepdim=True)
    return ((xf - mean) * torch.rsqrt(var + eps)).to(x.dtype)


class FeatureExtractor(nn.Module):
    """Table 3: per-vertex MLP (1x1 convs), each layer InstanceNorm + ReLU. `(..., V, in_dim) -> (..., V, C)`."""

    def __init__(self, channels: tuple[int, ...], in_dim: int = 3):
        super().__init__()
        widths = (in_dim, *channels)
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(widths[:-1], widths[1:]))

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        x = points
        for layer in self.layers:
            x = F.relu(instance_norm(layer(x)))
        return x


class SPAdaIN(nn.Module):
    """Table 5: InstanceNorm(x) * w(target) + b(target); the target's xyz sets a per-vertex scale and shift."""

    def __init__(self, dim: int):
        super().__init__()
        self.to_scale = nn.Linear(3, dim)
        self.to_shift = nn.Linear(3, dim)

    def forward(self, x: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        # x (B, T, V, C); target (B, V, 3) -> modulation (B, 1, V, C), shared by all frames
        target = target.unsqueeze(1)
        return instance_norm(x) * self.to_scale(target) + self.to_shift(target)


class SPAdaINResBlock(nn.Module):
    """Table 4 rows 13-19: two SPAdaIN -> 1x1 conv -> ReLU steps, plus one on the shortcut."""

    def __init__(self, dim: int):
        super().__init__()
        self.norm1, self.norm2, self.norm_skip = SPAdaIN(dim), SPAdaIN(dim), SPAdaIN(dim)
        self.fc1, self.fc2, self.fc_skip = nn.Linear(dim, dim), nn.Linear(dim, dim), nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        out = F.relu(self.fc1(self.norm1(x, target)))
        out = F.relu(self.fc2(self.norm2(out, target)))
        return out + F.relu(self.fc_skip(self.norm_skip(x, target)))


class VertexAttention(nn.Module):
    """Eq. 2-3: gamma-gated multi-head attention across the vertices of each frame.

    Self-attention takes q, k, v from `x`; cross-attention takes k, v from `memory` (the driving
    features) so that queries live on the target's vertices. `(B, T, V, C) -> (B, T, V, C)`.
    """

    def __init__(self, dim: int, heads: int, memory_dim: int | None = None):
        super().__init__()
        self.heads = heads
        self.to_q = nn.Linear(dim, dim)
        self.to_kv = nn.Linear(memory_dim or dim, 2 * dim)
        self.gamma = nn.Parameter(torch.zeros(1))

    def forward(self, x: torch.Tensor, memory: torch.Tensor | None = None) -> torch.Tensor:
        source = x if memory is None else memory
        # The einops views keep the head dim contiguous (stride 1), which the flash kernel requires.
        q = rearrange(self.to_q(x), "b t v (h d) -> (b t) h v d", h=self.heads)
        k, v = rearrange(self.to_kv(source), "b t v (two h d) -> two (b t) h v d", two=2, h=self.heads)
        out = F.scaled_dot_product_attention(q, k, v)
        return x + self.gamma * rearrange(out, "(b t) h v d -> b t v (h d)", b=x.shape[0])


class TemporalAttention(nn.Module):
    """Ours: gamma-gated multi-head attention of every vertex across the T frames of its window."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.heads = heads
        self.to_qkv = nn.Linear(dim, 3 * dim)
        self.gamma = nn.Parameter(torch.zeros(1))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        q, k, v = rearrange(self.to_qkv(x), "b t v (three h d) -> three (b v) h t d", three=3, h=self.heads)
        out = F.scaled_dot_product_attention(q, k, v)
        return x + self.gamma * rearrange(out, "(b v) h t d -> b t v (h d)", b=x.shape[0])


class EncoderStage(nn.Module):
    """Table 6 `conv -> AniFormer encoder`: width change, attention, then the target-modulated block."""

    def __init__(self, in_dim: int, dim: int, heads: int, config: AniFormerConfig, memory_dim: int):
        super().__init__()
        self.proj = nn.Linear(in_dim, dim)
        self.attention = VertexAttention(dim, heads, memory_dim if config.attention == "cross" else None)
        self.temporal = TemporalAttention(dim, heads) if config.temporal == "attention" else None
        self.block = SPAdaINResBlock(dim)

    def mix(self, x: torch.Tensor, memory: torch.Tensor | None) -> torch.Tensor:
        """Width change and attention: what the stage does across vertices (and frames)."""
        x = self.attention(self.proj(x), memory)
        return x if self.temporal is None else self.temporal(x)

    def forward(self, x: torch.Tensor, target: torch.Tensor, memory: torch.Tensor | None,
                checkpointed: bool = False) -> torch.Tensor:
        # Checkpointed in two parts, so that backward reruns either the attention or the block, never both at once.
        x = run_block(self.mix, checkpointed, x, memory)
        return run_block(self.block, checkpointed, x, target)


class AniFormer(nn.Module):
    """`model(driving (B, T, V1, 3), target (B, V2, 3)) -> (B, T, V2, 3)` (`(B, 1, V2, 3)` with the regression head);
    `faces (F, 3)` of the shared topology (or `(B, F, 3)`, one topology per batch) for `output="transfer"`."""

    def __init__(self, config: AniFormerConfig = AniFormerConfig()):
        super().__init__()
        self.config = config
        feature_dim = config.extractor_channels[-1]
        # transfer: each driving vertex also carries where the prior moves it (the correction's evidence)
        self.extractor = FeatureExtractor(config.extractor_channels, 6 if config.output == "transfer" else 3)
        self.target_extractor = FeatureExtractor(config.extractor_channels) if config.attention == "cross" else None
        self.temporal_embedding = nn.Parameter(torch.zeros(config.window, feature_dim))
        nn.init.trunc_normal_(self.temporal_embedding, std=0.02)
        widths = (feature_dim, *config.channels)
        self.stages = nn.ModuleList(
            EncoderStage(a, b, h, config, feature_dim)
            for a, b, h in zip(widths[:-1], widths[1:], config.stage_heads())
        )
        last = config.channels[-1]
        if config.head == "regression":
            self.to_xyz = nn.Sequential(nn.Linear(last, last), nn.ReLU(), nn.Linear(last, 3))
        else:
            self.to_xyz = nn.Linear(last, 3)
        if config.output != "absolute":  # start from the prior: copy-driver or the deformation transfer
            nn.init.zeros_(self.to_xyz[-1].weight if config.head == "regression" else self.to_xyz.weight)
            nn.init.zeros_(self.to_xyz[-1].bias if config.head == "regression" else self.to_xyz.bias)
        self.activation_checkpointing = False

    def prior(self, driving: torch.Tensor, target: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
        """output="transfer": the target deformed into each driving pose (`deformation_transfer`, without grad)."""
        return deformation_transfer(driving, target, faces)

    def forward(self, driving: torch.Tensor, target: torch.Tensor, faces: torch.Tensor | None = None) -> torch.Tensor:
        B, T, V1, _ = driving.shape
        V2 = target.shape[1]
        if T != self.config.window:
            raise ValueError(f"driving window has {T} frames, the model was built for window={self.config.window}")
        if self.config.output != "absolute" and V1 != V2:
            raise ValueError(f"output={self.config.output!r} needs driver and target of one topology; "
                             f"got {V1} and {V2} vertices")
        if self.config.output == "transfer" and faces is None:
            raise ValueError("output='transfer' needs the faces of the topology: model(driving, target, faces)")
        checkpointed = self.activation_checkpointing
        points, prior = driving, None
        if self.config.output == "transfer":
            prior = self.prior(driving, target, faces)
            points = torch.cat([driving, prior - driving], dim=-1)
        features = run_block(self.extractor, checkpointed, points) + self.temporal_embedding[:, None, :]  # eq. 1
        if self.config.attention == "cross":
            memory = features
            x = run_block(self.target_extractor, checkpointed, target).unsqueeze(1).expand(B, T, V2, -1)
        else:
            memory = None
            if self.config.pool_driving or V1 != V2:
                features = features.amax(dim=2, keepdim=True).expand(B, T, V2, -1)
            x = features
        for stage in self.stages:
            x = stage(x, target, memory, checkpointed)
        if self.config.head == "regression":
            x = x.mean(dim=1, keepdim=True)  # average over the sequence, one output mesh
        if self.config.output == "absolute":
            return 2 * torch.tanh(self.to_xyz(x))
        if prior is None:
            return driving[:, self.config.output_frames()] + self.to_xyz(x).to(driving.dtype)
        # bounding-box centred like the prior and every mesh the model sees (the correction would move the box)
        return center_bbox(prior[:, self.config.output_frames()] + self.to_xyz(x).to(driving.dtype))

    def forward_flops(self, v1: int, v2: int | None = None) -> int:
        """Matmul FLOPs (2 per multiply-add) of one forward window with V1 driving and V2 target
        vertices, counted from the layer plan. A training step costs ~3x that (forward + backward,
        as nanoGPT's `estimate_mfu` counts); model FLOP utilisation = 3 * this * windows/s / peak."""
        cfg = self.config
        v2 = v1 if v2 is None else v2
        T, feature_dim, cross = cfg.window, cfg.extractor_channels[-1], cfg.attention == "cross"

        def linear(rows: int, fan_in: int, fan_out: int) -> int:
            return 2 * rows * fan_in * fan_out

        widths = (3, *cfg.extractor_channels)
        per_point = sum(linear(1, a, b) for a, b in zip(widths[:-1], widths[1:]))
        flops = T * v1 * per_point + (v2 * per_point if cross else 0)  # the target's extractor: once per window
        in_dim = feature_dim
        for c in cfg.channels:
            kv_rows, kv_dim = (v1, feature_dim) if cross else (v2, c)
            flops += linear(T * v2, in_dim, c) + linear(T * v2, c, c) + linear(T * kv_rows, kv_dim, 2 * c)
            flops += 4 * T * v2 * kv_rows * c  # q k^T and A v over all heads (eq. 2)
            if cfg.temporal == "attention":
                flops += linear(T * v2, c, 3 * c) + 4 * v2 * T * T * c
            flops += 3 * (2 * linear(v2, 3, c) + linear(T * v2, c, c))  # 3 SPAdaIN (scale, shift per window) + fc
            in_dim = c
        last = cfg.channels[-1]
        if cfg.head == "regression":
            return flops + linear(v2, last, last) + linear(v2, last, 3)
        return flops + linear(T * v2, last, 3)
