"""Forward / train-step time and peak memory of AniFormer against a dense fp32 reference.

The reference is the same layer plan run the way the paper's code runs it: fp32 and attention
that materialises the V x V map (PyTorch's math SDPA kernel computes softmax(q k^T) explicitly).
dense-tf32 is that reference with every matmul on TF32 tensor cores
(`torch.set_float32_matmul_precision("high")`). The paper's code on an Ampere or newer GPU gets TF32 in
its Conv1d layers (PyTorch's default), not in its bmm attention, so this bounds its speed from above.
Ours: `F.scaled_dot_product_attention` with its fused kernels, bf16 autocast on GPUs with bf16;
ours-compiled: the same through `torch.compile` (`--compile-mode reduce-overhead` adds CUDA graphs).
`--activation-checkpointing` and `--attention-kernels cudnn flash efficient` apply to both. The
last column is the relative L2 error of a B=1 forward against the fp32 forward of the same initial
weights (attention gates opened to 0.5, so that attention counts), whose attention runs the exact
memory-efficient kernel where the device has one (the math kernel's V x V maps would not fit at
V = 12,272, T = 8), else the math kernel; the last names the
aten attention ops a training step ran (profiler), i.e. which SDPA kernel was really selected.
Each measurement runs in its own process so peak memory is not polluted by the previous one.
Throughput is also given as model FLOP/s: `AniFormer.forward_flops` (the layer plan's matmuls,
checked against torch's FLOP counter in tests/test_model.py) per forward, 3x that per training
step, as nanoGPT's `estimate_mfu` counts; MFU = that over `--peak-tflops` (the device's dense peak
for the dtype, e.g. ~989 for an H100 SXM in bf16; the design notes use ~790).

    python bench/model_bench.py --device cpu --vertices 1229 --window 3 --batch 1
    python bench/model_bench.py --device cuda --vertices 6890 12272 --batch 1 16 --peak-tflops 989 \
        --attention-kernels cudnn flash efficient
Prints one Markdown row per (implementation, V, batch).
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from contextlib import contextmanager

import torch

from aniformer import AniFormer, AniFormerConfig
from aniformer.model import ATTENTION_KERNELS, attention_kernels

IMPLEMENTATIONS = ("ours", "ours-compiled", "dense-fp32", "dense-tf32")


def open_gates(model: AniFormer) -> None:
    """gamma = 0.5 everywhere: at initialisation (gamma = 0) attention adds nothing to the output, so
    a numerics check would not see it."""
    with torch.no_grad():
        for name, p in model.named_parameters():
            if name.endswith("gamma"):
                p.fill_(0.5)


@contextmanager
def float32_matmul_precision(level: str):
    """torch.set_float32_matmul_precision(level) inside the block only ("high": TF32 on CUDA)."""
    previous = torch.get_float32_matmul_precision()
    torch.set_float32_matmul_precision(level)
    try:
        yield
    finally:
        torch.set_float32_matmul_precision(previous)


def profile_step(fn, device: str) -> tuple[str, list[tuple[str, float]], float]:
    """Profile one call of `fn`: the aten attention ops it ran (which SDPA kernel was really selected,
    also when compiled) and, on a GPU, its kernels by device time: ([(name, ms)] top 10, total ms)."""
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity, profile

    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device == "cuda" else [])
    with profile(activities=activities) as prof:
        fn()
        if device == "cuda":
            torch.cuda.synchronize()
    prefix = "aten::_scaled_dot_product_"
    names = sorted({e.name.removeprefix(prefix) for e in prof.events() if e.name.startswith(prefix)})
    kernels = sorted(((e.key, e.self_device_time_total / 1e3) for e in prof.key_averages()
                      if e.device_type == DeviceType.CUDA), key=lambda k: -k[1])
    return ", ".join(names) or "none (inlined)", kernels[:10], sum(ms for _, ms in kernels)


def measure(impl: str, device: str, vertices: int, window: int, batch: int, steps: int, threads: int,
            compile_mode: str = "default", activation_checkpointing: bool = False,
            kernels: tuple[str, ...] = (), heads: int | tuple[int, ...] = 8) -> dict:
    torch.manual_seed(0)
    if device == "cpu":
        torch.set_num_threads(threads)
    model = AniFormer(AniFormerConfig(window=window, heads=heads)).to(device)
    open_gates(model)
    optimizer = torch.optim.Adam(model.parameters(), lr=5e-5)
    driving = torch.randn(batch, window, vertices, 3, device=device) * 0.3
    target = torch.randn(batch, vertices, 3, device=device) * 0.3
    ours = impl.startswith("ours")
    matmul = "high" if impl == "dense-tf32" else torch.get_float32_matmul_precision()
    use_bf16 = ours and device == "cuda" and torch.cuda.is_bf16_supported()
    autocast = torch.autocast("cuda", torch.bfloat16, enabled=use_bf16)
    initial = {k: v.clone() for k, v in model.state_dict().items()}  # for the numerics check after the timing
    run = model
    if ours:
        model.activation_checkpointing = activation_checkpointing
        if impl == "ours-compiled":
            run = torch.compile(model, mode=compile_mode)
    else:
        kernels = ("math",)  # the V x V map in fp32, as the paper's code

    def sync():
        if device == "cuda":
            torch.cuda.synchronize()

    def forward():
        with torch.no_grad(), autocast, attention_kernels(kernels), float32_matmul_precision(matmul):
            return run(driving[:1], target[:1])

    def train_step():
        with float32_matmul_precision(matmul):  # backward too: outside autocast, as torch recommends
            with autocast, attention_kernels(kernels):
                loss = (run(driving, target) - driving).square().mean()
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
        optimizer.step()

    warmup_s = 0.0

    def timed(fn) -> float:
        nonlocal warmup_s
        start = time.perf_counter()
        for _ in range(3 if impl == "ours-compiled" else 1):  # warm-up: compilation, CUDA graph recording
            fn()
        sync()
        warmup_s += time.perf_counter() - start
        start = time.perf_counter()
        for _ in range(steps):
            fn()
        sync()
        return (time.perf_counter() - start) / steps

    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    forward_s = timed(forward)
    step_s = timed(train_step)
    if device == "cuda":
        peak_gib = torch.cuda.max_memory_allocated() / 2**30
    else:  # the process high-water mark above what model + inputs already held
        peak_gib = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss_before) / 2**20
    flops = model.forward_flops(vertices)
    ops, top_kernels, kernel_ms = profile_step(train_step, device)
    # Numerics: this implementation's forward against the exact fp32 forward, same initial weights.
    model.load_state_dict(initial)
    with torch.no_grad(), attention_kernels(["efficient", "math"]), float32_matmul_precision("highest"):
        reference = model(driving[:1], target[:1]).float()
    error = ((forward().float() - reference).norm() / reference.norm()).item()
    dtype = "bf16" if use_bf16 else "tf32" if impl == "dense-tf32" and device == "cuda" else "fp32"
    return dict(impl=impl, device=device, vertices=vertices, window=window, batch=batch,
                forward_ms=forward_s * 1e3, step_ms_per_sample=step_s * 1e3 / batch, peak_gib=peak_gib,
                dtype=dtype, relative_error=error, forward_tflops=flops / forward_s / 1e12,
                train_tflops=3 * flops * batch / step_s / 1e12, attention=ops,
                warmup_s=warmup_s, top_kernels=top_kernels, kernel_ms=kernel_ms)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--vertices", type=int, nargs="+", default=[1229])
    parser.add_argument("--batch", type=int, nargs="+", default=[1])
    parser.add_argument("--window", type=int, default=3)
    parser.add_argument("--steps", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    parser.add_argument("--impl", choices=IMPLEMENTATIONS, nargs="+", default=list(IMPLEMENTATIONS))
    parser.add_argument("--peak-tflops", type=float, default=None, help="dense peak of the device, for MFU")
    parser.add_argument("--compile-mode", default="default", help="torch.compile mode of ours-compiled")
    parser.add_argument("--activation-checkpointing", action="store_true", help="ours*: rerun each stage in backward")
    parser.add_argument("--attention-kernels", nargs="*", default=[], choices=sorted(ATTENTION_KERNELS),
                        help="ours*: SDPA kernels allowed, by preference (default: torch's choice)")
    parser.add_argument("--heads", type=int, nargs="+", default=[8],
                        help="attention heads, one count or one per stage (8 4 4 2: head dim 128 everywhere)")
    parser.add_argument("--one", action="store_true", help=argparse.SUPPRESS)  # child process: one measurement
    args = parser.parse_args()
    heads = args.heads[0] if len(args.heads) == 1 else tuple(args.heads)
    try:
        AniFormerConfig(heads=heads)
    except ValueError as e:
        parser.error(str(e))
    if args.one:
        print(json.dumps(measure(args.impl[0], args.device, args.vertices[0], args.window, args.batch[0],
                                 args.steps, args.threads, args.compile_mode, args.activation_checkpointing,
                                 tuple(args.attention_kernels), heads)))
        return
    options = ["--compile-mode", args.compile_mode, "--attention-kernels", *args.attention_kernels,
               "--heads", *map(str, args.heads)]
    if args.activation_checkpointing:
        options.append("--activation-checkpointing")
    print(f"Paper layer plan, heads per stage: {' '.join(map(str, args.heads))}\n")
    print("| impl | device | dtype | V | T | batch | forward B=1 (ms) | train step / sample (ms) | peak (GiB) "
          "| forward TFLOP/s | train TFLOP/s | train MFU | error vs fp32 | attention op (train step) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    profiles = []
    for v in args.vertices:
        for batch in args.batch:
            for impl in args.impl:
                cmd = [sys.executable, __file__, "--one", "--impl", impl, "--device", args.device,
                       "--vertices", str(v), "--batch", str(batch), "--window", str(args.window),
                       "--steps", str(args.steps), "--threads", str(args.threads), *options]
                run = subprocess.run(cmd, capture_output=True, text=True)
                if run.returncode != 0:
                    last = (run.stderr.strip().splitlines() or ["?"])[-1]
                    print(f"| {impl} | {args.device} | | {v} | {args.window} | {batch} | failed: {last[:80]} "
                          "| | | | | | | |")
                    continue
                r = json.loads(run.stdout.strip().splitlines()[-1])
                mfu = f"{r['train_tflops'] / args.peak_tflops:.1%}" if args.peak_tflops else ""
                print(f"| {r['impl']} | {r['device']} | {r['dtype']} | {v} | {r['window']} | {batch} | "
                      f"{r['forward_ms']:.1f} | {r['step_ms_per_sample']:.1f} | {r['peak_gib']:.2f} | "
                      f"{r['forward_tflops']:.3g} | {r['train_tflops']:.3g} | {mfu} | {r['relative_error']:.1e} | "
                      f"{r['attention']} |",
                      flush=True)
                profiles.append(r)
    for r in profiles:  # where a training step's device time goes (GPU only: CPU runs list no kernels)
        print(f"\n{r['impl']}, V={r['vertices']}, T={r['window']}, B={r['batch']}: warm-up {r['warmup_s']:.1f} s"
              + (f"; kernels of one profiled train step {r['kernel_ms']:.1f} ms, the top 10:" if r["top_kernels"] else ""))
        for name, ms in r["top_kernels"]:
            print(f"    {ms:8.2f} ms {ms / r['kernel_ms']:6.1%}  {name[:100]}")

if __name__ == "__main__":
    main()
