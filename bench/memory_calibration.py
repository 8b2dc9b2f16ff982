"""Calibrate and check the memory model (aniformer/memory.py) against real training steps.

Every config runs in a fresh subprocess: the training step of pipeline/train.py (AniFormer, Adam,
the eq. 6 loss with faces, `zero_grad(set_to_none=True)`, one CPU thread as a Ray worker with <= 1
CPU uses) for `--steps` steps. What is measured:

    cpu   peak RSS (VmHWM) minus the RSS just before the model is built, after a warm-up step
          of a tiny model has loaded every lazily-imported kernel and module (~100 MB that are
          process overhead, not step memory)
    cuda  torch.cuda.max_memory_allocated after the same warm-up (reset before the model is built);
          max_memory_reserved, what the caching allocator held from the device, is printed beside it

and compared with `MemoryEstimate.step` (parameters + Adam's moments + allocator factor x dynamic). `--fit` prints the
allocator factor that makes the median error zero.

    python bench/memory_calibration.py                       # the default CPU grid, Markdown table
    python bench/memory_calibration.py --mmap --steps 2      # RSS with glibc's mmap threshold fixed
    python bench/memory_calibration.py --device cuda --grid gpu
    python bench/memory_calibration.py --fit
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# (label, model config, V, batch, precision[, activation checkpointing]): activations of tens to
# hundreds of MB on CPU.
SMALL = {"channels": [64, 64, 64, 32], "extractor_channels": [16, 32, 64]}
MEDIUM = {"channels": [128, 128, 128, 64], "extractor_channels": [32, 64, 128]}
WIDE = {"channels": [256, 128, 128, 64], "extractor_channels": [32, 64, 256]}
PAPER = {"channels": [1024, 512, 512, 256], "extractor_channels": [64, 128, 1024]}

GRIDS = {
    "cpu": [
        ("small", dict(SMALL, window=3), 369, 2, "fp32"),
        ("small", dict(SMALL, window=8), 369, 4, "fp32"),
        ("small", dict(SMALL, window=2), 1229, 4, "fp32"),
        ("medium", dict(MEDIUM, window=3), 615, 4, "fp32"),
        ("medium", dict(MEDIUM, window=5), 615, 4, "fp32"),
        ("medium", dict(MEDIUM, window=3), 1229, 2, "fp32"),
        ("wide", dict(WIDE, window=3), 1229, 2, "fp32"),
        ("wide", dict(WIDE, window=2), 615, 8, "fp32"),
        ("paper", dict(PAPER, window=3), 369, 1, "fp32"),
        ("medium-cross", dict(MEDIUM, window=3, attention="cross"), 615, 4, "fp32"),
        ("medium, checkpointed", dict(MEDIUM, window=5), 615, 4, "fp32", True),
        ("wide, checkpointed", dict(WIDE, window=3), 1229, 2, "fp32", True),
        ("paper, checkpointed", dict(PAPER, window=3), 369, 1, "fp32", True),
    ],
    "gpu": [
        ("paper", dict(PAPER, window=3), 1229, 2, "bf16"),
        ("paper", dict(PAPER, window=3), 6890, 1, "bf16"),
        ("paper", dict(PAPER, window=3), 6890, 4, "bf16"),
        ("paper", dict(PAPER, window=6), 6890, 2, "bf16"),
        ("paper", dict(PAPER, window=3), 6890, 2, "fp16"),
        ("paper", dict(PAPER, window=3), 6890, 2, "fp32"),
        ("paper", dict(PAPER, window=3), 12272, 2, "bf16"),
        ("paper, checkpointed", dict(PAPER, window=3), 12272, 8, "bf16", True),
        ("paper, checkpointed", dict(PAPER, window=8), 12272, 2, "bf16", True),
    ],
}


def _rss_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096


def _peak_rss_bytes() -> int:
    """VmHWM: the peak RSS of this process image. Not ru_maxrss: Linux carries that over fork and
    exec, so a child of a big process (pytest after other tests) would report its parent's peak."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    raise RuntimeError("no VmHWM in /proc/self/status")


def child(spec: dict) -> dict:
    """Run the training steps of `spec` in this (fresh) process and return what was measured."""
    import time

    import torch

    from aniformer.losses import LossConfig, loss_terms
    from aniformer.models import build_model, model_config

    device = torch.device(spec["device"])
    if device.type == "cpu":
        torch.set_num_threads(spec.get("threads", 1))
    dtype = {"bf16": torch.bfloat16, "fp16": torch.float16}.get(spec["precision"])

    def steps(section: dict, V: int, B: int, n: int) -> None:
        torch.manual_seed(0)
        model = build_model(model_config(spec.get("model_name", "aniformer"), section)).to(device)
        model.activation_checkpointing = spec.get("activation_checkpointing", False)
        optimizer = torch.optim.Adam(model.parameters(), lr=5e-5)
        scaler = torch.amp.GradScaler(device.type, enabled=spec["precision"] == "fp16")
        T = model.config.window
        driving = torch.randn(B, T, V, 3, device=device)
        target = torch.randn(B, V, 3, device=device)
        truth = torch.randn(B, T, V, 3, device=device)
        faces = torch.randint(0, V, (B, 2 * V, 3), device=device)
        frames = model.config.output_frames()
        for _ in range(n):
            with torch.autocast(device.type, dtype=dtype, enabled=dtype is not None):
                pred = model(driving, target)
                terms = loss_terms(pred.float(), truth[:, frames], driving[:, frames], target, faces, LossConfig())
            scaler.scale(terms["total"]).backward()
            scaler.step(optimizer)
            scaler.update()
            optimizer.zero_grad(set_to_none=True)

    warm = dict(spec["model"], channels=[8], extractor_channels=[8])
    steps(warm, 16, 1, 2)  # loads every lazily-imported kernel and module: process overhead
    import gc

    gc.collect()
    if device.type == "cuda":
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats(device)
        base = torch.cuda.memory_allocated(device)
        base_reserved = torch.cuda.memory_reserved(device)
    else:
        base = _rss_bytes()
    started = time.perf_counter()
    steps(spec["model"], spec["vertices"], spec["batch"], spec["steps"])
    if device.type == "cuda":
        torch.cuda.synchronize()
        peak = torch.cuda.max_memory_allocated(device)
        reserved = torch.cuda.max_memory_reserved(device) - base_reserved
    else:
        peak = _peak_rss_bytes()
        reserved = None
    return {"measured": peak - base, "baseline": base, "reserved": reserved, "seconds": time.perf_counter() - started}


def measure(model: dict, vertices: int, batch: int, precision: str = "fp32", device: str = "cpu",
            steps: int = 2, model_name: str = "aniformer", timeout: float = 600, mmap: bool = False,
            activation_checkpointing: bool = False) -> dict:
    """Measure one config in a fresh subprocess; returns {"measured", "baseline", "seconds"} (bytes).

    `mmap`: run it with glibc's mmap threshold fixed (MALLOC_MMAP_THRESHOLD_=65536), so that freed
    activation buffers go back to the OS and peak RSS follows the live tensors.
    """
    env = {k: v for k, v in os.environ.items() if k != "MALLOC_MMAP_THRESHOLD_"}
    if mmap:
        env["MALLOC_MMAP_THRESHOLD_"] = "65536"
    spec = {"model": model, "vertices": vertices, "batch": batch, "precision": precision, "device": device,
            "steps": steps, "model_name": model_name, "activation_checkpointing": activation_checkpointing}
    out = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child", json.dumps(spec)],
                         capture_output=True, text=True, timeout=timeout, cwd=ROOT, env=env)
    if out.returncode != 0:
        raise RuntimeError(f"measurement failed: {out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def predict(model: dict, vertices: int, batch: int, precision: str, device: str, model_name: str = "aniformer",
            mmap: bool = False, activation_checkpointing: bool = False):
    from aniformer.memory import predict_step_memory
    from aniformer.models import model_config

    kind = "cuda" if device.startswith("cuda") else ("cpu-mmap" if mmap else "cpu")
    return predict_step_memory(model_config(model_name, model), vertices=vertices, batch=batch, precision=precision,
                               device=device, prefetch_batches=0, allocator_kind=kind,
                               activation_checkpointing=activation_checkpointing)


def main(argv: list[str]) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--device", default="cpu")
    p.add_argument("--grid", choices=sorted(GRIDS), default=None, help="default: cpu, or gpu with --device cuda")
    p.add_argument("--steps", type=int, default=8, help="training steps (CPU RSS settles after ~8)")
    p.add_argument("--mmap", action="store_true", help="fix glibc's mmap threshold: RSS follows live tensors")
    p.add_argument("--fit", action="store_true", help="print the allocator factor that zeroes the median error")
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        print(json.dumps(child(json.loads(args.child))))
        return
    cuda = args.device.startswith("cuda")
    grid = GRIDS[args.grid or ("gpu" if cuda else "cpu")]
    kind = "max_memory_allocated" if cuda else (
        "peak RSS - baseline" + (", mmap threshold fixed" if args.mmap else ", default malloc"))
    reserved = " max_memory_reserved (MiB) |" if cuda else ""
    print(f"| config | V | T | B | precision | predicted (MiB) | measured: {kind} (MiB) | error |{reserved} s/step |")
    print("|---|---|---|---|---|---|---|---|---|" + ("---|" if cuda else ""))
    errors, factors = [], []
    for label, model, V, B, precision, *checkpointed in grid:
        ac = bool(checkpointed and checkpointed[0])
        estimate = predict(model, V, B, precision, args.device, mmap=args.mmap, activation_checkpointing=ac)
        got = measure(model, V, B, precision, args.device, args.steps, mmap=args.mmap, activation_checkpointing=ac)
        error = estimate.step / got["measured"] - 1
        errors.append(error)
        dynamic = estimate.activations + estimate.workspace + estimate.inputs
        held = estimate.parameters + estimate.optimizer + estimate.ddp_buckets
        factors.append((got["measured"] - held) / dynamic)
        print(f"| {label} | {V} | {model['window']} | {B} | {precision} | {estimate.step / 2**20:.0f} | "
              f"{got['measured'] / 2**20:.0f} | {100 * error:+.1f}% |"
              + (f" {got['reserved'] / 2**20:.0f} |" if cuda else "") + f" {got['seconds'] / args.steps:.1f} |", flush=True)
    abs_errors = [abs(e) for e in errors]
    print(f"\nmean |error| {100 * statistics.mean(abs_errors):.1f}%, max |error| {100 * max(abs_errors):.1f}% "
          f"over {len(errors)} configs ({args.device})")
    if args.fit:
        print(f"fitted allocator factor (median of measured/predicted dynamic part): {statistics.median(factors):.3f}"
              f" (range {min(factors):.3f}..{max(factors):.3f})")


if __name__ == "__main__":
    main(sys.argv[1:])
