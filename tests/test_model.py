"""AniFormer model: shapes for every switch, gradients, gamma, config round trip, equivariance, memory."""

import json
import subprocess
import sys
import textwrap

import pytest
import torch
import yaml

from aniformer import AniFormer, AniFormerConfig
from aniformer.models import NPT, NPTConfig, build_model, copy_driver, model_config

TINY = dict(channels=(32, 16), extractor_channels=(8, 16, 32), heads=4)
SWITCHES = [
    dict(),
    dict(attention="cross"),
    dict(temporal="attention"),
    dict(attention="cross", temporal="attention"),
    dict(head="regression"),
    dict(pool_driving=True),
]


def open_gates(model) -> None:
    """gamma = 0.5 in every attention: at initialisation (gamma = 0) the attention paths add nothing."""
    with torch.no_grad():
        for name, p in model.named_parameters():
            if name.endswith("gamma"):
                p.fill_(0.5)


def test_paper_defaults_and_api_as_documented():
    cfg = AniFormerConfig(channels=(1024, 512, 512, 256), extractor_channels=(64, 128, 1024),
                          heads=8, window=3, attention="self", temporal="embedding", head="constraints")
    assert cfg == AniFormerConfig()
    assert AniFormerConfig(**cfg.to_dict()) == cfg
    assert AniFormerConfig(**yaml.safe_load(yaml.safe_dump(cfg.to_dict()))) == cfg
    assert AniFormerConfig(**json.loads(json.dumps(cfg.to_dict()))) == cfg


@pytest.mark.parametrize("bad", [dict(attention="both"), dict(temporal="rnn"), dict(head="mlp"),
                                 dict(channels=(30,), heads=8), dict(window=0), dict(heads=(4,)),
                                 dict(heads=(4, 3)), dict(heads=(4, 0)), dict(heads=2.0), dict(heads="4")])
def test_config_rejects_bad_values(bad):
    with pytest.raises(ValueError):
        AniFormerConfig(**{**TINY, **bad})


def test_per_stage_heads_set_each_stages_head_dim():
    """heads = channels / 128 keeps head dim 128 in every stage of the paper's plan; a list gives each
    stage its own count, in the config, its YAML/JSON form, the modules and the memory model."""
    from aniformer.memory import count_activations

    paper = AniFormerConfig(heads=[8, 4, 4, 2])
    assert paper.heads == (8, 4, 4, 2) and paper.to_dict()["heads"] == [8, 4, 4, 2]
    assert AniFormerConfig(**yaml.safe_load(yaml.safe_dump(paper.to_dict()))) == paper
    assert [c // h for c, h in zip(paper.channels, paper.stage_heads())] == [128] * 4
    assert AniFormerConfig(heads=8).stage_heads() == (8,) * 4
    cfg = AniFormerConfig(**{**TINY, "heads": [4, 2], "temporal": "attention"})
    model = AniFormer(cfg)
    assert [(s.attention.heads, s.temporal.heads) for s in model.stages] == [(4, 4), (2, 2)]
    assert model(torch.randn(1, 3, 20, 3), torch.randn(1, 20, 3)).shape == (1, 3, 20, 3)
    # same FLOPs (the head count splits the same matmuls), fewer log-sum-exp rows to keep
    same = AniFormerConfig(**{**TINY, "temporal": "attention"})
    assert model.forward_flops(20) == AniFormer(same).forward_flops(20)
    fewer, _ = count_activations(cfg, 2, (600, 600))
    assert fewer < count_activations(same, 2, (600, 600))[0]


@pytest.mark.parametrize("switch", SWITCHES, ids=lambda s: "-".join(f"{k}={v}" for k, v in s.items()) or "paper")
@pytest.mark.parametrize("v1,v2", [(40, 40), (40, 55)])
def test_output_shapes(switch, v1, v2):
    cfg = AniFormerConfig(**TINY, **switch)
    out = AniFormer(cfg)(torch.randn(2, 3, v1, 3), torch.randn(2, v2, 3))
    frames = 1 if cfg.head == "regression" else 3
    assert out.shape == (2, frames, v2, 3)
    assert out.shape[1] == len(range(3)[cfg.output_frames()])
    assert out.abs().max() <= 2  # 2 * tanh


def test_wrong_window_is_refused():
    with pytest.raises(ValueError, match="window"):
        AniFormer(AniFormerConfig(**TINY))(torch.randn(1, 4, 10, 3), torch.randn(1, 10, 3))


@pytest.mark.parametrize("switch", SWITCHES[:5], ids=str)
def test_gamma_starts_at_zero_and_gradients_reach_every_parameter(switch):
    torch.manual_seed(0)
    model = AniFormer(AniFormerConfig(**TINY, **switch))
    gammas = [p for n, p in model.named_parameters() if n.endswith("gamma")]
    assert gammas and all(g.item() == 0 for g in gammas)
    # With gamma = 0 the attention weights get no gradient (eq. 3), but gamma itself does.
    model(torch.randn(2, 3, 30, 3), torch.randn(2, 30, 3)).square().mean().backward()
    assert all(g.grad is not None and g.grad.abs().item() > 0 for g in gammas)
    model.zero_grad()
    with torch.no_grad():
        for g in gammas:
            g.fill_(0.5)
    model(torch.randn(2, 3, 30, 3), torch.randn(2, 30, 3)).square().mean().backward()
    missing = [n for n, p in model.named_parameters() if p.grad is None or p.grad.abs().sum() == 0]
    assert not missing, missing


def test_cross_attention_is_permutation_equivariant_in_the_target():
    torch.manual_seed(0)
    model = AniFormer(AniFormerConfig(**TINY, attention="cross", temporal="attention")).eval()
    with torch.no_grad():
        for p in model.parameters():  # make the attention paths active, not gated off
            if p.numel() == 1:
                p.fill_(0.7)
        driving, target = torch.randn(2, 3, 37, 3), torch.randn(2, 45, 3)
        perm = torch.randperm(45)
        out = model(driving, target)
        out_perm = model(driving, target[:, perm])
        driver_perm = model(driving[:, :, torch.randperm(37)], target)
    torch.testing.assert_close(out_perm, out[:, :, perm], atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(driver_perm, out, atol=1e-5, rtol=1e-4)  # and invariant in the driver


def test_npt_and_copy_driver():
    npt = NPT(NPTConfig(extractor_channels=(8, 16, 32), channels=(35, 16)))
    assert npt(torch.randn(2, 3, 20, 3), torch.randn(2, 20, 3)).shape == (2, 3, 20, 3)
    assert npt(torch.randn(2, 3, 20, 3), torch.randn(2, 25, 3)).shape == (2, 3, 25, 3)
    # NPT is frame by frame: a frame's output does not depend on the other frames.
    driving, target = torch.randn(1, 3, 20, 3), torch.randn(1, 20, 3)
    changed = driving.clone()
    changed[:, 2] += 1
    torch.testing.assert_close(npt(driving, target)[:, :2], npt(changed, target)[:, :2])
    copied = copy_driver(driving + 5, target)
    torch.testing.assert_close(copied.amax(2) + copied.amin(2), torch.zeros(1, 3, 3), atol=1e-6, rtol=0)
    with pytest.raises(ValueError, match="equal vertex counts"):
        copy_driver(driving, torch.randn(1, 21, 3))
    assert isinstance(build_model(model_config("aniformer", TINY)), AniFormer)
    with pytest.raises(ValueError, match="unknown model"):
        model_config("limp", {})


MEMORY_PROBE = textwrap.dedent("""
    import resource, sys, torch
    from aniformer import AniFormer, AniFormerConfig
    torch.set_num_threads(1)
    v = int(sys.argv[1])
    model = AniFormer(AniFormerConfig(channels=(64,), extractor_channels=(16, 64), heads=1)).eval()
    driving, target = torch.randn(1, 3, v, 3), torch.randn(1, v, 3)
    with torch.no_grad():
        model(driving[:, :, :64], target[:, :64])  # warm up allocator and kernels
        before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        model(driving, target)
    print((resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024)
""")


def test_forward_memory_grows_linearly_not_quadratically_in_vertices():
    def peak_mb(v):
        out = subprocess.run([sys.executable, "-c", MEMORY_PROBE, str(v)], capture_output=True, text=True, check=True)
        return float(out.stdout.strip())

    frames, width = 3, 64
    for v in (12_000, 24_000):
        activation_mb = frames * v * width * 4 / 2**20  # one (T, V, C) fp32 activation
        dense_map_mb = frames * v * v * 4 / 2**20  # one V x V attention map per frame
        peak = peak_mb(v)
        # ~7 activations' worth was measured at V=32k; a dense kernel needs >= one V x V map (4-7 GB here).
        assert peak < 16 * activation_mb, (v, peak, activation_mb)
        assert peak < dense_map_mb / 20, (v, peak, dense_map_mb)


@pytest.mark.parametrize("switch", SWITCHES, ids=lambda s: "-".join(f"{k}={v}" for k, v in s.items()) or "paper")
def test_attention_runs_on_the_fused_kernels_alone(switch):
    """With the math kernel ruled out, every attention call must still find a fused (flash or
    memory-efficient) kernel: a non-contiguous head dim or a materialised mask would raise here.
    The same q/k/v layout is what the GPU's flash/cuDNN kernels need (CPU has a flash kernel too)."""
    from torch.nn.attention import SDPBackend, sdpa_kernel

    torch.manual_seed(0)
    model = AniFormer(AniFormerConfig(**TINY, **switch))
    driving, target = torch.randn(2, 3, 40, 3), torch.randn(2, 55 if switch.get("pool_driving") else 40, 3)
    with sdpa_kernel([SDPBackend.MATH]):
        reference = model(driving, target)
    with sdpa_kernel([SDPBackend.FLASH_ATTENTION, SDPBackend.EFFICIENT_ATTENTION]):
        out = model(driving, target)
        out.square().mean().backward()
    torch.testing.assert_close(out, reference, atol=1e-5, rtol=1e-4)


def test_bf16_autocast_stays_close_to_fp32():
    """The mixed-precision path of training (bf16 autocast; instance-norm statistics in fp32)."""
    torch.manual_seed(0)
    model = AniFormer(AniFormerConfig(**TINY, attention="cross", temporal="attention"))
    open_gates(model)
    driving, target = torch.randn(2, 3, 60, 3) * 0.3, torch.randn(2, 60, 3) * 0.3
    reference = model(driving, target)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        low = model(driving, target)
    assert low.dtype == torch.bfloat16
    relative = (low.float() - reference).norm() / reference.norm()
    assert 0 < relative < 0.03, relative


@pytest.mark.parametrize("switch", SWITCHES, ids=lambda s: "-".join(f"{k}={v}" for k, v in s.items()) or "paper")
@pytest.mark.parametrize("v1,v2", [(40, 40), (40, 55)])
def test_forward_flops_match_torch_flop_counter(switch, v1, v2):
    """The analytic count behind the benchmark's MFU equals what torch counts op by op (the math
    SDPA kernel is used here because the counter has no formula for the CPU flash kernel)."""
    from torch.nn.attention import SDPBackend, sdpa_kernel
    from torch.utils.flop_counter import FlopCounterMode

    model = AniFormer(AniFormerConfig(**TINY, **switch))
    with FlopCounterMode(display=False) as counter, sdpa_kernel([SDPBackend.MATH]), torch.no_grad():
        model(torch.randn(2, 3, v1, 3), torch.randn(2, v2, 3))
    assert counter.get_total_flops() == 2 * model.forward_flops(v1, v2)


def _gradients(model, driving, target, run=None):
    """Output and parameter gradients of `run` (default: `model`; or e.g. its compiled wrapper)."""
    model.zero_grad(set_to_none=True)
    out = (model if run is None else run)(driving, target)
    out.square().mean().backward()
    return out.detach(), {n: p.grad.clone() for n, p in model.named_parameters()}


@pytest.mark.parametrize("name,config", [
    ("aniformer", dict(TINY)),
    ("aniformer", dict(TINY, attention="cross", temporal="attention")),
    ("npt", dict(channels=(35, 16), extractor_channels=(8, 16, 32))),
], ids=["paper", "cross-temporal", "npt"])
def test_activation_checkpointing_keeps_outputs_and_gradients(name, config):
    """The execution switch of train.activation_checkpointing: same outputs and gradients; inference
    (no grad) takes the plain path. What it saves: tests/test_memory.py."""
    torch.manual_seed(0)
    model = build_model(model_config(name, config))
    open_gates(model)
    driving, target = torch.randn(2, 3, 50, 3), torch.randn(2, 50, 3)
    plain_out, plain_grads = _gradients(model, driving, target)
    model.activation_checkpointing = True
    out, grads = _gradients(model, driving, target)
    torch.testing.assert_close(out, plain_out, rtol=0, atol=0)
    for n, g in grads.items():
        torch.testing.assert_close(g, plain_grads[n], rtol=1e-5, atol=1e-7, msg=n)
    with torch.no_grad():
        torch.testing.assert_close(model(driving, target), plain_out, rtol=0, atol=0)


def test_attention_kernels_restricts_and_orders_the_sdpa_kernels():
    """train.attention_kernels / bench --attention-kernels: only the named kernels may run (CPU has
    math and flash; the CUDA-only ones must fail here, which shows that the restriction holds)."""
    from aniformer.model import attention_kernels

    torch.manual_seed(0)
    model = AniFormer(AniFormerConfig(**TINY))
    driving, target = torch.randn(1, 3, 30, 3), torch.randn(1, 30, 3)
    default = model(driving, target)
    for names in (["flash"], ["math"], ["cudnn", "flash", "math"], []):
        with attention_kernels(names):
            torch.testing.assert_close(model(driving, target), default, atol=1e-6, rtol=1e-5)
    for names in (["efficient"], ["cudnn"]):
        with attention_kernels(names), pytest.raises(RuntimeError, match="No viable backend"):
            model(driving, target)


@pytest.mark.slow
def test_compiled_model_matches_eager(repo_root):
    """train.compile's path (torch.compile, inductor's C++ backend on CPU) with activation checkpointing:
    the compiled forward and gradients equal the eager ones. Model and batch are configs/tiny.yaml's
    (369 vertices), so that the compiled training job of tests/test_train.py finds these kernels in
    inductor's on-disk cache instead of compiling them again."""
    from aniformer.cli.args import load_config

    config = load_config(repo_root / "configs/tiny.yaml")
    torch.manual_seed(0)
    model = build_model(model_config(config["model"]["name"], {k: v for k, v in config["model"].items() if k != "name"}))
    open_gates(model)
    B, T = config["train"]["batch_size"], config["data"]["window"]
    driving, target = torch.randn(B, T, 369, 3) * 0.3, torch.randn(B, 369, 3) * 0.3
    model.activation_checkpointing = True
    eager_out, eager_grads = _gradients(model, driving, target)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as the job's worker (0.5 CPU): inductor's cache key includes the thread count
    try:
        out, grads = _gradients(model, driving, target, run=torch.compile(model))
    finally:
        torch.set_num_threads(threads)
    torch.testing.assert_close(out, eager_out, rtol=1e-4, atol=1e-5)
    scale = max(g.abs().max().item() for g in eager_grads.values())  # biases before a norm have ~0 gradients
    for n, g in grads.items():
        torch.testing.assert_close(g, eager_grads[n], rtol=1e-3, atol=1e-5 * scale, msg=n)


def test_model_bench_reports_the_kernel_really_run_and_the_error(bench_module):
    """bench/model_bench.py's columns that the GPU rows rely on: the attention op a training step ran
    (fused for ours, the V x V math kernel for the reference) and the error against fp32."""
    measure = bench_module("model_bench").measure

    ours = measure("ours", "cpu", vertices=48, window=3, batch=2, steps=1, threads=1, activation_checkpointing=True,
                   heads=(8, 4, 4, 2))  # head dim 128 in every stage
    assert "flash_attention_for_cpu" in ours["attention"] and "math" not in ours["attention"]
    assert 0 < ours["relative_error"] < 1e-5  # the same fp32 maths through another kernel
    reference = measure("dense-fp32", "cpu", vertices=48, window=3, batch=2, steps=1, threads=1)
    assert reference["attention"] == "attention_math" and reference["relative_error"] == 0
    tf32 = measure("dense-tf32", "cpu", vertices=48, window=3, batch=2, steps=1, threads=1)
    assert tf32["attention"] == "attention_math" and tf32["dtype"] == "fp32"  # TF32 exists on CUDA only
    assert torch.get_float32_matmul_precision() == "highest"  # restored for the rest of the process
    # the rates are the counted FLOPs (forward_flops, checked against torch's counter above) over the measured
    # times: one sample forward, and a training step of the batch at 3x the forward
    flops = AniFormer(AniFormerConfig(window=3, heads=(8, 4, 4, 2))).forward_flops(48)
    assert ours["forward_tflops"] == pytest.approx(flops / ours["forward_ms"] / 1e9, rel=1e-9)
    assert ours["train_tflops"] == pytest.approx(3 * flops / ours["step_ms_per_sample"] / 1e9, rel=1e-9)
