"""Losses (eq. 4, 5, L_rec) and PMD on hand-computed cases."""

import pytest
import torch

from aniformer.losses import LossConfig, appearance_loss, loss_terms, motion_loss, reconstruction_loss
from aniformer.metrics import PMD_SCALE, pmd, pmd_per_frame

TETRA = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
TETRA_FACES = torch.tensor([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])  # closed: 6 edges, 12 half-edges
EDGE_SQ = torch.tensor([1.0, 1, 1, 2, 2, 2])  # squared edge lengths of TETRA


def sequence(seed=0, t=4, v=30):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(2, t, v, 3, generator=g)


def test_identical_meshes_give_zero():
    gt = sequence()
    assert reconstruction_loss(gt, gt) == 0
    assert motion_loss(gt, gt) == 0
    target = TETRA.expand(2, -1, -1)
    assert appearance_loss(target.unsqueeze(1).expand(2, 3, 4, 3), target, TETRA_FACES) == 0
    terms = loss_terms(gt, gt, gt, gt[:, 0], torch.tensor([[0, 1, 2]]), LossConfig())
    assert terms["rec"] == 0 and terms["motion"] == 0


@pytest.mark.parametrize("form", ["absolute", "squared"])
def test_uniformly_scaled_motion_has_zero_motion_loss(form):
    driving = sequence(v=50)
    assert motion_loss(2.5 * driving + 1.0, driving, form) == pytest.approx(0, abs=1e-6)
    # ... and a motion that is not proportional to the driver is penalised.
    jerky = driving.clone()
    jerky[:, 2] *= 3
    assert motion_loss(jerky, driving, form) > 0.1


def test_motion_loss_with_different_vertex_counts_and_short_windows():
    driving = sequence(v=50)
    pred = 2 * driving[:, :, :25]  # a proportional motion on another vertex count
    assert torch.isfinite(motion_loss(pred, driving))
    assert motion_loss(sequence(t=2), sequence(seed=1, t=2)) == 0  # eq. 4 needs T >= 3


def test_motion_loss_printed_form_is_the_signed_difference():
    driving = torch.zeros(1, 3, 1, 3)
    driving[0, :, 0, 0] = torch.tensor([0.0, 1, 2])  # driver moves 1 per frame
    pred = torch.zeros(1, 3, 1, 3)
    pred[0, :, 0, 0] = torch.tensor([0.0, 1, 3])  # output moves 1 then 2: ratios 1 then 4
    assert motion_loss(pred, driving, "printed") == pytest.approx(-3)
    assert motion_loss(pred, driving, "absolute") == pytest.approx(3)
    assert motion_loss(pred, driving, "squared") == pytest.approx(9)


def test_known_edge_stretch_gives_known_appearance_loss():
    target = TETRA.unsqueeze(0)
    stretched = (2 * TETRA).expand(1, 3, 4, 3)  # every squared edge length x4: differences 3 * EDGE_SQ
    half_edges = 2  # each undirected edge is visited from both of its vertices
    expected_abs = half_edges * (3 * EDGE_SQ).sum() / 4  # / V
    assert appearance_loss(stretched, target, TETRA_FACES, "absolute") == pytest.approx(expected_abs.item())
    assert appearance_loss(stretched, target, TETRA_FACES, "squared") == pytest.approx(
        (half_edges * (3 * EDGE_SQ).square().sum() / 4).item())
    shrunk = (0.5 * TETRA).expand(1, 3, 4, 3)
    assert appearance_loss(shrunk, target, TETRA_FACES, "printed") < 0  # why the printed form is ill-posed
    # Per-sample faces (vertex shuffling): a permuted target with remapped faces gives the same loss.
    perm = torch.tensor([2, 0, 3, 1])
    inverse = torch.argsort(perm)
    faces = torch.stack([TETRA_FACES, inverse[TETRA_FACES]])
    batch_pred = torch.stack([2 * TETRA, 2 * TETRA[perm]]).unsqueeze(1)
    batch_target = torch.stack([TETRA, TETRA[perm]])
    per_sample = appearance_loss(batch_pred, batch_target, faces)
    assert per_sample == pytest.approx(expected_abs.item())


def test_loss_terms_weighted_sum_and_bad_form():
    pred, gt = sequence(0), sequence(1)
    faces = torch.tensor([[0, 1, 2], [2, 3, 4]])
    cfg = LossConfig(rec=1.0, motion=0.1, appearance=0.01)
    terms = loss_terms(pred, gt, gt, gt[:, 0], faces, cfg)
    expected = terms["rec"] + 0.1 * terms["motion"] + 0.01 * terms["appearance"]
    torch.testing.assert_close(terms["total"], expected)
    with pytest.raises(ValueError, match="form"):
        LossConfig(form="l2")


def test_pmd_on_known_offset():
    gt = sequence()
    pred = gt + torch.tensor([0.01, 0.0, 0.0])
    assert pmd(pred, gt).item() * PMD_SCALE == pytest.approx(1.0, rel=1e-4)
    pred = gt.clone()
    pred[:, 1] += torch.tensor([0.0, 0.02, 0.0])  # only frame 1 is off, by 2 cm
    per_frame = pmd_per_frame(pred, gt) * PMD_SCALE
    torch.testing.assert_close(per_frame, torch.tensor([[0.0, 4, 0, 0]] * 2), atol=1e-4, rtol=0)
