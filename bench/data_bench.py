"""Data benchmark: mesh-bank generation speed and pair-assembly throughput (docs/benchmarks.md, "Data").

    python bench/data_bench.py [--out bench/results/data.json] [--skip-notoes] [--skip-train]

Generation: a fixed small bank (8 motion instances, 30 frames, 11 identities -> 1,320 meshes)
at 1,229 and 12,272 vertices, with 1 and 2 Ray Data workers on a local Ray instance; each
setting runs twice: "cold" includes starting worker processes (import torch/anny), "warm"
reuses them (what a second generation in the same driver sees). Pair assembly at 1,229 vertices,
T=3, target shuffling: the numpy ``PairSampler`` alone, Ray Data ``iter_torch_batches`` on the
driver, and inside a 2-worker ``TorchTrainer`` reading ``get_dataset_shard`` (what training sees).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from pipeline import data
from pipeline.data.synthetic import body_model

BANK = dict(
    seed=0,
    frames=30,
    driving_identities=4,
    unseen_driving_identities=1,
    target_identities_train=4,
    target_identities_test=3,
    actions=("jumping_jacks", "punching", "knee_raises", "shake_arms"),
    heldout_actions=("shake_arms",),
    instances_per_action=2,
    unseen_instance_fraction=0.2,
    pairs_per_epoch=2000,
    eval_pairs=500,
    window=3,
    shuffle="target",
    center="mesh",
)


def bench_generation(topology: str, workers: int, root: Path) -> dict:
    cfg = data.DataConfig(topology=topology, **BANK)
    runs = []
    for attempt in ("cold", "warm"):
        out = root / f"{topology}-{workers}-{attempt}"
        start = time.perf_counter()
        manifest = data.generate_bank(cfg, out, workers=workers, progress=False)
        seconds = time.perf_counter() - start
        runs.append(seconds)
        if attempt == "warm":
            size = sum(s["bytes"] for s in manifest.shards)
            shutil.rmtree(out)
        else:
            keep = out
    meshes = manifest.counts["meshes"]
    return {
        "topology": topology,
        "vertices": manifest.num_vertices,
        "workers": workers,
        "meshes": meshes,
        "shards": manifest.counts["shards"],
        "mb": round(size / 1e6, 1),
        "cold_s": round(runs[0], 2),
        "warm_s": round(runs[1], 2),
        "cold_meshes_per_s": round(meshes / runs[0]),
        "warm_meshes_per_s": round(meshes / runs[1]),
        "bank": str(keep),
    }


def bench_numpy_pairs(bank_dir: str, batch_size: int, seconds: float = 5.0) -> float:
    sampler = data.PairSampler.from_dir(bank_dir)
    n, i, start = 0, 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        sampler.batch("train", 0, np.arange(i, i + batch_size) % sampler.pairs_per_epoch)
        n, i = n + batch_size, i + batch_size
    return n / (time.perf_counter() - start)


def bench_ray_pairs(bank_dir: str, batch_size: int, pairs: int = 8000) -> dict:
    ds = data.pair_dataset(bank_dir, "train", pairs=pairs)
    start, n, first = time.perf_counter(), 0, None
    for batch in ds.iter_torch_batches(batch_size=batch_size):
        n += len(batch["index"])
        first = first or time.perf_counter() - start
    total = time.perf_counter() - start
    return {
        "pairs": n,
        "seconds": round(total, 2),
        "first_batch_s": round(first, 2),
        "pairs_per_s": round(n / total),
        "steady_pairs_per_s": round((n - batch_size) / (total - first)),
    }


def bench_train_feed(bank_dir: str, batch_size: int, pairs: int = 8000) -> dict:
    import ray.train
    from ray.train import ScalingConfig
    from ray.train.torch import TorchTrainer

    out = Path(tempfile.mkdtemp(prefix="feed-"))

    def loop(config):
        shard = ray.train.get_dataset_shard("train")
        n, start, first = 0, time.perf_counter(), None
        for batch in shard.iter_torch_batches(batch_size=config["batch_size"]):
            n += len(batch["index"])
            first = first or time.perf_counter() - start
        total = time.perf_counter() - start
        rank = ray.train.get_context().get_world_rank()
        (Path(config["out"]) / f"{rank}.json").write_text(json.dumps({"n": n, "s": total, "first": first}))

    ds = data.pair_dataset(bank_dir, "train", pairs=pairs)
    trainer = TorchTrainer(
        loop,
        train_loop_config={"batch_size": batch_size, "out": str(out)},
        datasets={"train": ds},
        scaling_config=ScalingConfig(num_workers=2, resources_per_worker={"CPU": 0.5}),
        run_config=ray.train.RunConfig(storage_path=str(out / "runs"), name="feed"),
    )
    trainer.fit()
    ranks = [json.loads((out / f"{r}.json").read_text()) for r in (0, 1)]
    seconds = max(r["s"] for r in ranks)
    first = max(r["first"] for r in ranks)
    n = sum(r["n"] for r in ranks)
    shutil.rmtree(out, ignore_errors=True)
    return {
        "pairs": n,
        "seconds": round(seconds, 2),
        "first_batch_s": round(first, 2),
        "pairs_per_s": round(n / seconds),
        "steady_pairs_per_s": round(n / max(1e-9, seconds - first)),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default="bench/results/data.json")
    p.add_argument("--skip-notoes", action="store_true", help="skip the 12,272-vertex generation")
    p.add_argument("--skip-train", action="store_true", help="skip the TorchTrainer feed measurement")
    args = p.parse_args()
    import logging

    import ray

    logging.getLogger("ray.data").setLevel(logging.ERROR)
    ray.init(include_dashboard=True, dashboard_host="127.0.0.1", num_cpus=os.cpu_count())
    results = {"cpus": os.cpu_count(), "load_avg_start": os.getloadavg(), "generation": [], "pairs": {}}
    root = Path(tempfile.mkdtemp(prefix="data-bench-"))
    try:
        topologies = ["notoes_collapse10pc"] + ([] if args.skip_notoes else ["notoes"])
        for topology in topologies:
            body_model(topology)  # a cold Anny build (once per machine) is not what we time
            for workers in (1, 2):
                r = bench_generation(topology, workers, root)
                print(json.dumps(r), flush=True)
                results["generation"].append(r)
        bank = next(r["bank"] for r in results["generation"] if r["vertices"] == 1229)
        for b in (2, 32):
            results["pairs"][f"numpy_B{b}"] = round(bench_numpy_pairs(bank, b))
            print("numpy", b, results["pairs"][f"numpy_B{b}"], flush=True)
        for b in (2, 32):
            results["pairs"][f"ray_data_driver_B{b}"] = bench_ray_pairs(bank, b)
            print("ray data", b, results["pairs"][f"ray_data_driver_B{b}"], flush=True)
        if not args.skip_train:
            for b in (2, 32):
                results["pairs"][f"torch_trainer_2x0.5cpu_B{b}"] = bench_train_feed(bank, b)
                print("train feed", b, results["pairs"][f"torch_trainer_2x0.5cpu_B{b}"], flush=True)
    finally:
        shutil.rmtree(root, ignore_errors=True)
        results["load_avg_end"] = os.getloadavg()
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=1) + "\n")
    print(f"results: {out}")


if __name__ == "__main__":
    main()
