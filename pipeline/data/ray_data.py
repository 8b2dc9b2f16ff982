"""The Ray Data part of the data path: generating a bank on the cluster, the bank a job trains on,
pair datasets for Ray Train, and quieting Ray Data's console output."""

from __future__ import annotations

import hashlib
import io
import math
import os
from pathlib import Path

import numpy as np
import pyarrow as pa
import ray
import torch
from ray.data import DataContext, TaskPoolStrategy
from tqdm import tqdm

from aniformer.cli.outputs import staged_output_dir
from aniformer.errors import UserError
from pipeline.data.bank import check_bank_matches, read_faces
from pipeline.data.config import DataConfig
from pipeline.data.manifest import (
    FACES,
    MANIFEST,
    SHARD_DIR,
    Manifest,
    finish_bank,
    npy_bytes,
    read_manifest,
    shard_name,
    write_file,
)
from pipeline.data.pairs import PairSampler, PairSource, pair_source
from pipeline.data.plan import plan_bank, shard_layout
from pipeline.data.synthetic import body_model, generate_shard


def _generate_shards(batch: dict, manifest: Manifest, layout: list[list[int]]) -> dict:
    """Ray Data task: shard indices -> Parquet bytes (worker processes, and their body model, are
    reused from task to task)."""
    body = body_model(manifest.topology)
    threads = torch.get_num_threads()
    out = {"shard": [], "payload": [], "rows": [], "faces": []}
    try:
        for shard in batch["shard"]:
            seqs = layout[int(shard)]
            out["shard"].append(int(shard))
            out["payload"].append(generate_shard(manifest, seqs))
            out["rows"].append(int(sum(manifest.sequences["frames"][s] for s in seqs)))
            out["faces"].append(npy_bytes(body.faces) if int(shard) == 0 else b"")
    finally:
        torch.set_num_threads(threads)  # the worker process may run other tasks next
    return {
        "shard": np.array(out["shard"], np.int64),
        "payload": np.array(out["payload"], dtype=object),
        "rows": np.array(out["rows"], np.int64),
        "faces": np.array(out["faces"], dtype=object),
    }


def _cluster_cpus() -> float:
    return float(ray.cluster_resources().get("CPU", 1.0))


def worker_plan(workers: int, units: int) -> tuple[int, float]:
    """(actors, CPUs per actor) for ``units`` work units on the connected cluster.

    Fractional CPUs leave room for Ray Data's own tasks (2 x 1 CPU on a 2-CPU node was measured to
    hang Ray Data silently)."""
    cpus = _cluster_cpus()
    workers = workers or max(1, int(cpus))
    workers = max(1, min(workers, units))
    per_actor = min(1.0, cpus / (workers + 1)) if workers >= cpus else 1.0
    return workers, round(per_actor, 3)


def quiet_ray_data() -> None:
    """No Ray Data progress bars or execution banners from this process, nor from the Ray Train
    workers it starts next (Ray Train copies the driver's DataContext to them): in a job's log they
    are a line per refresh for every dataset of every epoch. Progress is ours (tqdm, MLflow)."""
    ctx = DataContext.get_current()
    ctx.enable_progress_bars = False
    ctx.print_on_execution_start = False


def generate_bank(cfg: DataConfig, out_dir: str | os.PathLike, *, workers: int | None = None, progress: bool = True) -> Manifest:
    """Generate the synthetic mesh bank of ``cfg`` into ``out_dir`` (new or empty) on the connected
    Ray cluster; returns the manifest. Needs ``ray.init`` first. Same ``cfg`` -> same bytes."""
    out_dir = Path(out_dir)
    if out_dir.exists() and any(out_dir.iterdir()):
        raise UserError(f"{out_dir} is not empty")
    out_dir.mkdir(parents=True, exist_ok=True)
    manifest = plan_bank(cfg)
    layout = shard_layout(manifest, cfg.shard_mb)
    n_workers, cpus = worker_plan(workers if workers is not None else cfg.workers, len(layout))
    quiet_ray_data()
    ds = ray.data.from_items([{"shard": i} for i in range(len(layout))], override_num_blocks=len(layout))
    ds = ds.map_batches(
        _generate_shards,
        fn_kwargs={"manifest": manifest, "layout": layout},
        batch_size=1,
        compute=TaskPoolStrategy(size=n_workers),
        num_cpus=cpus,
    )
    shards, faces = [], None
    bar = tqdm(
        total=manifest.counts["meshes"],
        unit="mesh",
        disable=not progress,
        desc=f"bank {cfg.topology} x{n_workers}",
    )
    with bar:
        for row in ds.iter_rows():
            i = int(row["shard"])
            payload = row["payload"]
            if i == 0:
                faces = np.load(io.BytesIO(row["faces"]), allow_pickle=False)
            path = shard_name(i)
            write_file(out_dir / path, payload)
            seqs = layout[i]
            shards.append(
                {
                    "path": path,
                    "rows": int(row["rows"]),
                    "sequences": [seqs[0], seqs[-1] + 1],
                    "first_row": manifest.sequences["first_row"][seqs[0]],
                    "bytes": len(payload),
                    "sha256": hashlib.sha256(payload).hexdigest(),
                }
            )
            bar.update(int(row["rows"]))
    if len(shards) != len(layout):
        raise RuntimeError(f"generation returned {len(shards)} of {len(layout)} shards")
    return finish_bank(out_dir, manifest, faces, shards)


def prepare_bank(cfg: DataConfig, bank_dir: str | os.PathLike, *, generate: bool) -> tuple[Manifest | None, np.ndarray]:
    """(manifest, faces) of the bank a job trains on: checked against ``cfg`` if it exists, else
    generated there when ``generate`` (the job's own ``OUT/bank``), else a `UserError`. Any other source
    (the stream) needs no bank: (None, its faces).

    Generation is staged (``aniformer.cli.outputs.staged_output_dir``): the bank appears complete or not at all, and a
    killed job's staging directory is removed by the next one. A bank directory holding only what an
    unstaged generation leaves (shards, faces, no manifest) is taken as incomplete and regenerated."""
    if cfg.source != "bank":
        return None, pair_source(cfg, bank_dir).faces
    bank_dir = Path(bank_dir)
    if (bank_dir / MANIFEST).is_file():
        manifest = read_manifest(bank_dir)
        check_bank_matches(manifest, cfg)
    elif generate:
        leftovers = sorted(p.name for p in bank_dir.iterdir()) if bank_dir.is_dir() else []
        incomplete = bool(leftovers) and all(n in (SHARD_DIR, FACES) or n.startswith(".") for n in leftovers)
        if leftovers and not incomplete:
            raise UserError(f"{bank_dir} is not empty and holds no mesh bank ({MANIFEST} missing); "
                            "move it away or pass --bank DIR")
        print(f"generating the mesh bank into {bank_dir}"
              + (" (replacing an incomplete one) ..." if incomplete else " ..."), flush=True)
        with staged_output_dir(bank_dir, overwrite=incomplete) as tmp:
            manifest = generate_bank(cfg, tmp)
    else:
        raise UserError(f"--bank {bank_dir}: no mesh bank there (make one with jobs/generate_data.py)")
    return manifest, read_faces(bank_dir, manifest)


_SAMPLER_CACHE: dict = {}  # the pair sampler of this worker process, by object ref


def _assemble(batch: dict, sampler_ref: list, split: str, n: int, first_epoch: int, first_index: int) -> dict:
    """Ray Data task: ids ``epoch_offset * n + index`` -> assembled pairs ``first_index + index``."""
    key = sampler_ref[0].hex()
    sampler = _SAMPLER_CACHE.get(key)
    if sampler is None:
        _SAMPLER_CACHE.clear()  # one bank per worker process at a time (it lives in the object store)
        sampler = _SAMPLER_CACHE[key] = ray.get(sampler_ref[0])
    ids = np.asarray(batch["id"], np.int64)
    epochs = first_epoch + ids // n
    parts = [sampler.batch(split, int(e), first_index + (ids % n)[epochs == e], n=n) for e in np.unique(epochs)]
    if len(parts) == 1:
        return parts[0]
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def pair_dataset(
    bank: str | os.PathLike | PairSource,
    split: str = "train",
    cfg: DataConfig | None = None,
    *,
    epochs: int = 1,
    first_epoch: int = 0,
    pairs: int | None = None,
    first_index: int = 0,
    batch_size: int | None = None,
    num_cpus: float = 0.5,
    concurrency: int | None = None,
    rows_per_block: int | None = None,
):
    """A Ray Dataset of the pairs of ``epochs`` consecutive epochs of ``split`` (``pairs`` per
    epoch; default ``pairs_per_epoch`` for train, ``eval_pairs`` otherwise), epoch by epoch: pairs
    ``first_index`` to ``first_index + pairs - 1`` of each (a stream's; another topology's share of an epoch).

    Columns: driving (T, V, 3) float32, target (V, 3), ground_truth (T, V, 3), target_faces (F, 3)
    int64, and int64 ids index, epoch, motion, start, driving_identity, target_identity. Pair ``i``
    of epoch ``e`` depends only on (seed, split, e, i). The bank is loaded once on the driver and
    shared through the object store (zero-copy for tasks on the same node). For Ray Train pass
    it as ``datasets={"train": ds}`` and read ``get_dataset_shard("train").iter_torch_batches(...)``;
    one pass over the dataset covers all ``epochs`` (use the ``epoch`` column or count steps).

    ``bank`` is a bank directory or a ``PairSource`` (``pair_source``); a ``StreamPairs`` makes every
    pair on the fly in the Ray Data tasks, which then scale with the CPUs Ray Data gets, and has
    only the ``index`` and ``epoch`` id columns.

    ``rows_per_block`` (pairs per Ray Data block) defaults to the sampler's ``block_pairs`` if it
    has one, else ~64 MB of pairs, at most 1,024, and
    ``batch_size`` (pairs assembled per call) to ``min(256, rows_per_block)``: measured on 2 cores,
    256-pair blocks gave a quarter of the throughput of 1,024-pair ones.
    """
    sampler = PairSampler.from_dir(bank, cfg) if isinstance(bank, (str, os.PathLike)) else bank
    sampler.split(split)  # unknown or empty split: fail here, in the caller, with one line
    n = sampler.default_pairs(split) if pairs is None else int(pairs)
    if n < 1 or epochs < 1 or first_epoch < 0 or first_index < 0:
        raise UserError(f"pairs ({n}) and epochs ({epochs}) must be >= 1, first_epoch ({first_epoch}) and "
                        f"first_index ({first_index}) >= 0")
    V, F = sampler.num_vertices, len(sampler.faces)
    pair_bytes = (2 * sampler.window + 1) * V * 12 + F * 24
    rows_per_block = rows_per_block or getattr(sampler, "block_pairs", None) or max(8, min(1024, int(64e6 // pair_bytes)))
    batch_size = batch_size or min(256, rows_per_block)
    ref = ray.put(sampler)
    total = n * epochs
    # Pair ids as blocks made on the driver: `ray.data.range` would run read tasks that each ask for a
    # whole CPU, which never schedule when fractional trainers leave less than one CPU on every node.
    chunks = np.array_split(np.arange(total, dtype=np.int64), max(1, math.ceil(total / rows_per_block)))
    ds = ray.data.from_arrow([pa.table({"id": chunk}) for chunk in chunks])
    return ds.map_batches(
        _assemble,
        fn_kwargs={"sampler_ref": [ref], "split": split, "n": n, "first_epoch": first_epoch, "first_index": first_index},
        batch_size=batch_size,
        num_cpus=num_cpus,
        compute=TaskPoolStrategy(size=concurrency) if concurrency else None,
    )
