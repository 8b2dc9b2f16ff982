"""Point-wise mesh Euclidean distance (PMD, the paper's eq. 7) and its per-frame variant.

PMD = 1/T 1/V sum_t sum_v ||M_v^t - G_v^t||^2 on bounding-box-centred meshes in metres; tables
report it multiplied by `PMD_SCALE` (the paper's "x 1e-4" units).
"""

from __future__ import annotations

import torch

PMD_SCALE = 1e4


def pmd_per_frame(pred: torch.Tensor, ground_truth: torch.Tensor) -> torch.Tensor:
    """`(..., T, V, 3)` pairs -> `(..., T)`: mean over vertices of the squared Euclidean distance."""
    return (pred - ground_truth).square().sum(-1).mean(-1)


def pmd(pred: torch.Tensor, ground_truth: torch.Tensor) -> torch.Tensor:
    """Mean PMD over frames (and any batch dims) as a scalar tensor, in metres squared."""
    return pmd_per_frame(pred, ground_truth).mean()
