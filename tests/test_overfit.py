"""A tiny AniFormer overfits one pair (loss falls >= 10x) within a minute on CPU."""

import torch
import trimesh

from aniformer import AniFormer, AniFormerConfig
from aniformer.losses import LossConfig, loss_terms


def test_tiny_model_overfits_one_pair():
    torch.manual_seed(0)
    sphere = trimesh.creation.icosphere(subdivisions=2)  # 162 vertices, closed
    base = torch.tensor(sphere.vertices, dtype=torch.float32) * 0.5
    faces = torch.tensor(sphere.faces)
    stretch = torch.tensor([1.0, 1.15, 1.3])  # the driving "motion": stretching along z, frame by frame
    driving = torch.stack([base * torch.tensor([1, 1, s]) for s in stretch]).unsqueeze(0)
    target = (base * torch.tensor([0.8, 1.2, 1.0])).unsqueeze(0)  # another "identity"
    gt = torch.stack([target[0] * torch.tensor([1, 1, s]) for s in stretch]).unsqueeze(0)

    model = AniFormer(AniFormerConfig(channels=(64, 32), extractor_channels=(16, 32, 64), heads=4))
    optimizer = torch.optim.Adam(model.parameters(), lr=2e-3)
    losses = []
    for _ in range(150):
        terms = loss_terms(model(driving, target), gt, driving, target, faces, LossConfig())
        optimizer.zero_grad()
        terms["total"].backward()
        optimizer.step()
        losses.append(terms["total"].item())
    assert min(losses[-10:]) < losses[0] / 10, (losses[0], losses[-10:])
