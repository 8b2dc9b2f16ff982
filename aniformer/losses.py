"""The paper's objective (eq. 6): L = lambda_rec L_rec + lambda_m L_m (eq. 4) + lambda_a L_a (eq. 5).

Shapes: prediction and ground truth `(B, T, V2, 3)`, driving `(B, T, V1, 3)`, target `(B, V2, 3)`,
target faces `(B, F, 3)` (per sample, because vertex shuffling permutes faces) or `(F, 3)`.
Everything is vectorised over batch and frames.

As printed, eq. 4 and eq. 5 are sums of signed differences and can be driven to minus infinity
(shrink the output to shrink its edges, eq. 5). `form` picks how each difference d enters:
    "absolute" (default)  |d|   - L1, well-posed, same units as the printed form
    "squared"             d^2
    "printed"             d     - exactly as printed, for reproduction only
Eq. 4 compares the motion *magnitudes* ||M_t - M_{t-1}||^2 / ||G_t - G_{t-1}||^2 of consecutive frame
pairs (G = the driving sequence): it is zero when the output moves proportionally to the driver,
e.g. for a uniformly scaled copy of the motion. The squared norms are averaged over vertices so
that driver and target may have different vertex counts.
Eq. 5's double sum over every vertex p and each neighbour u of p visits every half-edge of the
mesh once; for the closed body meshes used here, that is each undirected edge twice, exactly as
printed. L_rec is NPT's point-wise L2 (mean squared coordinate error).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from aniformer.config import Section

FORMS = ("absolute", "squared", "printed")
# Driving frames that move less than ~1 mm RMS are treated as moving 1 mm: keeps the eq. 4 ratio finite.
MIN_MOTION = 1e-6


@dataclass(frozen=True)
class LossConfig(Section):
    """Weights of eq. 6 (paper: 1, 5e-4, 5e-4) and the form of eq. 4/5's differences."""

    rec: float = 1.0
    motion: float = 5e-4
    appearance: float = 5e-4
    form: str = "absolute"

    def __post_init__(self):
        super().__post_init__()
        if self.form not in FORMS:
            raise ValueError(f"form must be one of {FORMS}, got {self.form!r}")
        if min(self.rec, self.motion, self.appearance) < 0:
            raise ValueError("loss weights must be >= 0")


def _apply_form(d: torch.Tensor, form: str) -> torch.Tensor:
    if form == "absolute":
        return d.abs()
    if form == "squared":
        return d.square()
    return d


def reconstruction_loss(pred: torch.Tensor, ground_truth: torch.Tensor) -> torch.Tensor:
    return (pred - ground_truth).square().mean()


def motion_loss(pred: torch.Tensor, driving: torch.Tensor, form: str = "absolute") -> torch.Tensor:
    """Eq. 4; zero for windows of fewer than 3 frames (it needs two consecutive motions)."""
    if pred.shape[1] < 3:
        return pred.new_zeros(())
    moved = (pred[:, 1:] - pred[:, :-1]).square().sum(-1).mean(-1)  # (B, T-1)
    drove = (driving[:, 1:] - driving[:, :-1]).square().sum(-1).mean(-1)
    ratio = moved / drove.clamp_min(MIN_MOTION)
    return _apply_form(ratio[:, :-1] - ratio[:, 1:], form).mean()


def appearance_loss(pred: torch.Tensor, target: torch.Tensor, faces: torch.Tensor,
                    form: str = "absolute") -> torch.Tensor:
    """Eq. 5: squared edge lengths of every output frame against those of the target mesh."""
    B, T, V, _ = pred.shape
    if faces.dim() == 2:
        faces = faces.expand(B, -1, -1)
    start = faces.reshape(B, -1)  # half-edge (f[i], f[i+1 mod 3]) of every face
    end = faces.roll(-1, dims=-1).reshape(B, -1)

    def squared_lengths(x: torch.Tensor) -> torch.Tensor:  # x (B, T', V, 3) -> (B, T', 3F)
        gather = lambda idx: x.gather(2, idx[:, None, :, None].expand(-1, x.shape[1], -1, 3))  # noqa: E731
        return (gather(start) - gather(end)).square().sum(-1)

    d = squared_lengths(pred) - squared_lengths(target.unsqueeze(1))
    return _apply_form(d, form).sum(-1).mean() / V


def loss_terms(pred: torch.Tensor, ground_truth: torch.Tensor, driving: torch.Tensor, target: torch.Tensor,
               target_faces: torch.Tensor, config: LossConfig) -> dict[str, torch.Tensor]:
    """Every term and their weighted sum ("total"); pred, ground truth and driving cover the same frames."""
    terms = {
        "rec": reconstruction_loss(pred, ground_truth),
        "motion": motion_loss(pred, driving, config.form),
        "appearance": appearance_loss(pred, target, target_faces, config.form),
    }
    terms["total"] = (config.rec * terms["rec"] + config.motion * terms["motion"]
                      + config.appearance * terms["appearance"])
    return terms
