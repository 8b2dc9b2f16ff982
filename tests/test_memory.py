"""The memory model (aniformer/memory.py): its layer-plan count against autograd's own, its peak
against measured peak RSS of real training steps, and the batch gate."""

from __future__ import annotations

import pytest
import torch

from aniformer.losses import LossConfig, loss_terms
from aniformer.memory import count_activations, parameter_count, predict_step_memory
from aniformer.models import build_model, model_config
from pipeline.memory_gate import plan_batch

TINY = {"channels": [64, 32], "extractor_channels": [16, 64], "heads": 8}


def saved_activation_bytes(name: str, config: dict, B: int, V1: int, V2: int, precision: str,
                           activation_checkpointing: bool = False) -> int:
    """Bytes of the distinct storages autograd saves for backward (forward + loss), parameters excluded."""
    torch.manual_seed(0)
    model = build_model(model_config(name, config))
    model.activation_checkpointing = activation_checkpointing
    T = model.config.window
    driving, target = torch.randn(B, T, V1, 3), torch.randn(B, V2, 3)
    faces = torch.randint(0, V2, (B, 2 * V2, 3))
    parameters = {p.untyped_storage().data_ptr() for p in model.parameters()}
    seen = {}

    def pack(x):
        storage = x.untyped_storage()
        if storage.data_ptr() not in parameters:
            seen[storage.data_ptr()] = storage.nbytes()
        return x

    dtype = {"bf16": torch.bfloat16}.get(precision)
    with torch.autograd.graph.saved_tensors_hooks(pack, lambda x: x):
        with torch.autocast("cpu", dtype=dtype, enabled=dtype is not None):
            out = model(driving, target)
        frames = model.config.output_frames()
        loss_terms(out.float(), torch.randn_like(out.float()), driving[:, frames], target, faces, LossConfig())
    if dtype is not None:  # autocast's low-precision weight copies are counted as workspace, not activations
        return sum(seen.values()) - sum(p.numel() * 2 for p in model.parameters() if p.dim() == 2)
    return sum(seen.values())


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
@pytest.mark.parametrize("name,config,B,V1,V2", [
    ("aniformer", dict(TINY, window=3), 2, 400, 400),
    ("aniformer", dict(TINY, window=6), 1, 400, 400),
    ("aniformer", dict(TINY, window=1), 4, 400, 400),
    ("aniformer", dict(TINY, window=3, attention="cross"), 2, 400, 300),
    ("aniformer", dict(TINY, window=3), 2, 400, 300),  # self-attention with V1 != V2: pooled driver
    ("aniformer", dict(TINY, window=3, temporal="attention"), 2, 400, 400),
    ("aniformer", dict(TINY, window=3, temporal="attention", heads=[8, 2]), 2, 400, 400),  # per-stage heads
    ("aniformer", dict(TINY, window=3, head="regression"), 2, 400, 400),
    ("aniformer", dict(channels=[256, 128], extractor_channels=[64, 128, 256], window=3), 1, 300, 300),
    ("npt", dict(channels=[65, 33], extractor_channels=[16, 64], window=3), 2, 400, 400),
])
def test_activation_count_matches_autograd(name, config, B, V1, V2, precision):
    cfg = model_config(name, config)
    predicted, _ = count_activations(name, cfg, B, (V1, V2), precision)
    actual = saved_activation_bytes(name, config, B, V1, V2, precision)
    assert predicted == pytest.approx(actual, rel=0.06), (predicted / 2**20, actual / 2**20)


@pytest.mark.parametrize("name,config", [
    ("aniformer", dict(TINY, window=3)),
    ("aniformer", dict(TINY, window=3, attention="cross", temporal="attention")),
    ("npt", dict(channels=[35, 16], extractor_channels=[8, 16, 32], window=3)),
], ids=["paper", "cross-temporal", "npt"])
def test_activation_checkpointing_saves_a_fraction(name, config):
    """With train.activation_checkpointing autograd keeps only the checkpointed parts' inputs."""
    plain = saved_activation_bytes(name, config, 2, 50, 50, "fp32")
    assert saved_activation_bytes(name, config, 2, 50, 50, "fp32", activation_checkpointing=True) < 0.6 * plain


def test_parameters_are_counted_exactly_without_allocating():
    for name, config in [("aniformer", dict(TINY, window=3)), ("aniformer", {}), ("npt", {})]:
        model = build_model(model_config(name, config))
        assert parameter_count(name, model.config) == sum(p.numel() for p in model.parameters())


def test_estimate_grows_with_batch_window_vertices_and_has_no_vv_term():
    def step(**kw):
        args = dict(vertices=1000, batch=2, precision="fp32", device="cpu") | kw
        window = args.pop("window", 3)
        return predict_step_memory("aniformer", dict(TINY, window=window), **args).activations

    assert step(batch=4) == pytest.approx(2 * step(batch=2), rel=0.01)
    assert step(window=6) == pytest.approx(2 * step(window=3), rel=0.05)  # the (B, 1, V, C) modulations do not grow
    assert step(vertices=4000) == pytest.approx(4 * step(vertices=1000), rel=0.01)  # linear in V: no V x V map
    assert step(precision="bf16") < step()
    assert step(activation_checkpointing=True) < 0.7 * step()  # two stages: the larger one is rerun
    paper = predict_step_memory("aniformer", {"window": 3}, vertices=6890, batch=16, precision="bf16", device="cuda")
    assert 20 < paper.total_gb < 80  # design.md measured 28-54 GiB for this step on an H100


def test_gate_keeps_adjusts_or_skips():
    kw = dict(vertices=6890, precision="fp16", device="cuda")
    paper = {"window": 3}
    ok = plan_batch("aniformer", paper, batch=1, limit_gb=32, **kw)
    assert ok.status == "ok" and ok.batch_size == 1 and ok.grad_accumulation == 1
    adjusted = plan_batch("aniformer", paper, batch=16, limit_gb=16, **kw)
    assert adjusted.status == "adjusted_memory" and adjusted.predicted_gb <= 16 < adjusted.requested_gb
    assert adjusted.batch_size * adjusted.grad_accumulation == 16  # the effective batch is kept
    skipped = plan_batch("aniformer", {"window": 8}, batch=2, limit_gb=1, **kw)
    assert skipped.status == "skipped_memory" and skipped.predicted_gb > 1
    assert plan_batch("aniformer", paper, batch=64, limit_gb=None, **kw).status == "ok"


@pytest.mark.slow
@pytest.mark.parametrize("model,V,B,checkpointed", [
    ({"channels": [64, 64, 64, 32], "extractor_channels": [16, 32, 64], "window": 3}, 369, 4, False),
    ({"channels": [64, 64, 64, 32], "extractor_channels": [16, 32, 64], "window": 8}, 369, 2, False),
    ({"channels": [64, 64, 64, 32], "extractor_channels": [16, 32, 64], "window": 2}, 1229, 2, False),
    ({"channels": [128, 128, 128, 64], "extractor_channels": [32, 64, 128], "window": 5}, 615, 2, False),
    ({"channels": [128, 128, 128, 64], "extractor_channels": [32, 64, 128], "window": 5}, 615, 4, True),
])
def test_prediction_within_25_percent_of_measured_peak_rss(model, V, B, checkpointed, bench_module):
    """Peak RSS of real training steps in a fresh process (minus its RSS before the model is built,
    after a warm-up), with glibc's mmap threshold fixed so that RSS follows the live tensors: the
    step's own memory, not the allocator's history (default malloc: see docs/benchmarks.md).
    With activation checkpointing too: kept stage outputs + the largest part rerun in backward."""
    calibration = bench_module("memory_calibration")
    estimate = calibration.predict(model, V, B, "fp32", "cpu", mmap=True, activation_checkpointing=checkpointed)
    got = calibration.measure(model, V, B, "fp32", "cpu", steps=2, mmap=True, activation_checkpointing=checkpointed)
    measured = got["measured"]
    assert measured > 50 * 2**20, "too small to measure above the noise"
    assert estimate.step == pytest.approx(measured, rel=0.25), (estimate.step / 2**20, got)
