"""The memory model (aniformer/memory.py): its count on fake tensors against the same count of real CPU steps
and against what autograd saves, its peak against measured peak RSS of real training steps, and the batch gate."""

from __future__ import annotations

import pytest
import torch

from aniformer.losses import LossConfig, loss_terms
from aniformer.memory import parameter_count, predict_step_memory, step_memory
from aniformer.models import build_model, model_config
from pipeline.memory_gate import plan_batch

TINY = {"channels": [64, 32], "extractor_channels": [16, 64], "heads": 8}
VARIANTS = [  # (model, config, V1, V2)
    ("aniformer", dict(TINY, window=3), 60, 60),
    ("aniformer", dict(TINY, window=3, output="residual"), 60, 60),
    ("aniformer", dict(TINY, window=3, output="transfer"), 60, 60),
    ("aniformer", dict(TINY, window=3, attention="cross"), 60, 45),
    ("aniformer", dict(TINY, window=3), 60, 45),  # self-attention with V1 != V2: pooled driver
    ("aniformer", dict(TINY, window=4, temporal="attention", heads=[8, 2]), 60, 60),  # per-stage heads
    ("aniformer", dict(TINY, window=3, head="regression"), 60, 60),
    ("npt", dict(channels=[65, 33], extractor_channels=[16, 64], window=3), 60, 60),
    ("npt", dict(channels=[65, 33], extractor_channels=[16, 64], window=3), 60, 45),
]
IDS = ["paper", "residual", "transfer", "cross", "pooled", "temporal-attention", "regression", "npt", "npt-pooled"]


@pytest.fixture(autouse=True)
def one_thread():
    """The real steps here are tiny: on a loaded 2-core machine a second thread costs more than their work."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def real_batch(config, B: int, V1: int, V2: int) -> tuple[torch.Tensor, ...]:
    """(driving, target, ground truth, faces) as train.py gets them; the faces are a closed strip (2 V2 triangles)."""
    T = config.window
    v = torch.arange(V2)
    faces = torch.stack([v, (v + 1) % V2, (v + 2) % V2], -1).repeat(2, 1)
    return torch.randn(B, T, V1, 3), torch.randn(B, V2, 3), torch.randn(B, T, V2, 3), faces.expand(B, -1, -1)


def real_model(name: str, section: dict, checkpointed: bool = False):
    torch.manual_seed(0)
    model = build_model(model_config(name, section))
    model.activation_checkpointing = checkpointed
    return model


@pytest.mark.parametrize("checkpointed", [False, True], ids=["plain", "checkpointed"])
@pytest.mark.parametrize("precision", ["fp32", "bf16"])
@pytest.mark.parametrize("name,section,V1,V2", VARIANTS, ids=IDS)
def test_fake_count_equals_a_real_cpu_step(name, section, V1, V2, precision, checkpointed):
    """The prediction's count, on fake tensors, is the count of a real step of the same size, byte for byte
    (transfer: the real deformation transfer against the zeros prior the fake count substitutes)."""
    model = real_model(name, section, checkpointed)
    batch = real_batch(model.config, 2, V1, V2)
    step_memory(model, *batch, precision=precision)  # warm-up: roma builds a constant on its first call
    activations, workspace = step_memory(model, *batch, precision=precision)
    estimate = predict_step_memory(model.config, vertices=(V1, V2), batch=2, faces=2 * V2, precision=precision,
                                   prefetch_batches=0, activation_checkpointing=checkpointed)
    assert (estimate.activations, estimate.workspace) == (activations, workspace)
    assert estimate.inputs == sum(t.nelement() * t.element_size() for t in batch)  # faces: one copy per sample
    assert estimate.parameters == 4 * sum(p.numel() for p in model.parameters())


@pytest.mark.parametrize("checkpointed", [False, True], ids=["plain", "checkpointed"])
@pytest.mark.parametrize("precision", ["fp32", "bf16"])
@pytest.mark.parametrize("name,section,V1,V2", [VARIANTS[0], VARIANTS[2], VARIANTS[3], VARIANTS[8]],
                         ids=["paper", "transfer", "cross", "npt-pooled"])
def test_activations_are_what_autograd_saves(name, section, V1, V2, precision, checkpointed):
    """What is alive when backward starts is the distinct storages autograd saves for it (parameters and the
    batch excluded; with checkpointing, the parts' inputs) plus what the loop holds: the prediction and the loss."""
    model = real_model(name, section, checkpointed)
    batch = driving, target, truth, faces = real_batch(model.config, 2, V1, V2)
    activations, _ = step_memory(model, *batch, precision=precision)
    model.zero_grad(set_to_none=True)
    skip = {t.untyped_storage()._cdata for t in [*model.parameters(), *batch]}
    saved = {}

    def pack(x):
        if x.untyped_storage()._cdata not in skip:
            saved[x.untyped_storage()._cdata] = x.untyped_storage().nbytes()
        return x

    frames = model.config.output_frames()
    dtype = {"bf16": torch.bfloat16}.get(precision)
    with torch.autograd.graph.saved_tensors_hooks(pack, lambda x: x):
        with torch.autocast("cpu", dtype=dtype, enabled=dtype is not None):
            pred = model(driving, target, faces)
        terms = loss_terms(pred.float(), truth[:, frames], driving[:, frames], target, faces, LossConfig())
    held = {t.untyped_storage()._cdata: t.untyped_storage().nbytes() for t in [pred, *terms.values()]}
    assert activations == sum(saved.values()) + sum(n for key, n in held.items() if key not in saved)


def test_parameters_are_counted_exactly_without_allocating():
    for name, config in [("aniformer", dict(TINY, window=3)), ("aniformer", {}), ("npt", {})]:
        model = build_model(model_config(name, config))
        assert parameter_count(model.config) == sum(p.numel() for p in model.parameters())


def test_estimate_grows_with_batch_window_vertices_and_has_no_vv_term():
    def step(window=3, **kw):
        estimate = predict_step_memory(model_config("aniformer", dict(TINY, window=window)),
                                       **(dict(vertices=1000, batch=2) | kw))
        return estimate.activations + estimate.workspace

    assert step(batch=4) == pytest.approx(2 * step(batch=2), rel=0.01)
    assert step(window=6) == pytest.approx(2 * step(window=3), rel=0.05)  # the (B, 1, V, C) modulations do not grow
    assert step(vertices=4000) == pytest.approx(4 * step(vertices=1000), rel=0.01)  # linear in V: no V x V map
    assert step(precision="bf16") < 0.8 * step()
    assert step(activation_checkpointing=True) < 0.6 * step()  # two stages: one part is rerun at a time
    paper = predict_step_memory(model_config("aniformer", {"window": 3}), vertices=6890, batch=16, precision="bf16",
                                device="cuda")
    assert 20 < paper.total_gb < 80  # design.md measured 28-54 GiB for this step on an H100


def test_gate_keeps_adjusts_or_skips():
    kw = dict(vertices=6890, precision="fp16", device="cuda")
    paper = model_config("aniformer", {"window": 3})
    ok = plan_batch(paper, batch=1, limit_gb=32, **kw)
    assert ok.status == "ok" and ok.batch_size == 1 and ok.grad_accumulation == 1
    adjusted = plan_batch(paper, batch=16, limit_gb=16, **kw)
    assert adjusted.status == "adjusted_memory" and adjusted.predicted_gb <= 16 < adjusted.requested_gb
    assert adjusted.batch_size * adjusted.grad_accumulation == 16  # the effective batch is kept
    skipped = plan_batch(model_config("aniformer", {"window": 8}), batch=2, limit_gb=1, **kw)
    assert skipped.status == "skipped_memory" and skipped.predicted_gb > 1
    assert plan_batch(paper, batch=64, limit_gb=None, **kw).status == "ok"


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
    With activation checkpointing too: kept inputs + the part rerun in backward."""
    calibration = bench_module("memory_calibration")
    estimate = calibration.predict(model, V, B, "fp32", "cpu", mmap=True, activation_checkpointing=checkpointed)
    got = calibration.measure(model, V, B, "fp32", "cpu", steps=2, mmap=True, activation_checkpointing=checkpointed)
    measured = got["measured"]
    assert measured > 50 * 2**20, "too small to measure above the noise"
    assert estimate.step == pytest.approx(measured, rel=0.25), (estimate.step / 2**20, got)
