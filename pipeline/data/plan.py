"""The bank plan: identities, motion instances, the sequences a bank holds, splits and the shard
layout; metadata only, no vertices, a pure function of the config."""

from __future__ import annotations

import math

from aniformer.synth.bodies import TOPOLOGIES, sample_identities
from pipeline.data.config import BANK_SPLITS, EXECUTION_FIELDS, DataConfig, assign_motions, derive_seed
from pipeline.data.manifest import Manifest, new_manifest


def split_table(identities: list[dict], motions: list[dict]) -> dict:
    """``BANK_SPLITS`` resolved: split name -> its motion ids, target identity ids and description."""
    groups_t = {g: [i["id"] for i in identities if i["role"] == "target" and i["split"] == g] for g in ("train", "test")}
    splits = {}
    for name, (motion_group, target_group, description) in BANK_SPLITS.items():
        splits[name] = {
            "motions": [m["id"] for m in motions if m["split"] == motion_group],
            "targets": groups_t[target_group],
            "description": description,
        }
    return splits


def sequences_for(identities: list[dict], motions: list[dict], splits: dict) -> list[tuple[int, int]]:
    """(identity, motion) pairs the bank must hold, motion-major (a motion's driver first)."""
    needed = {(m["driver"], m["id"]) for m in motions}
    for split in splits.values():
        needed.update((t, m) for t in split["targets"] for m in split["motions"])
    return sorted(needed, key=lambda im: (im[1], im[0] != motions[im[1]]["driver"], im[0]))


def plan_bank(cfg: DataConfig) -> Manifest:
    """The manifest of the bank ``cfg`` describes, minus the shard list (no vertices computed)."""
    n_drv, n_tr, n_te = cfg.driving_identities, cfg.target_identities_train, cfg.target_identities_test
    n_seen = n_drv - cfg.unseen_driving_identities
    identity_seed = derive_seed(cfg.seed, "identities")
    phenotypes = sample_identities(n_drv + n_tr + n_te, identity_seed)
    identities = []
    for i in range(n_drv + n_tr + n_te):
        if i < n_drv:
            role, split, name = "driver", "seen" if i < n_seen else "unseen", f"driver-{i:03d}"
        elif i < n_drv + n_tr:
            role, split, name = "target", "train", f"target-{i - n_drv:03d}"
        else:
            role, split, name = "target", "test", f"target-{i - n_drv:03d}"
        identities.append(
            {
                "id": i,
                "name": name,
                "role": role,
                "split": split,
                "phenotype": [float(x) for x in phenotypes[i]],
            }
        )
    motions = assign_motions(cfg)
    for m in motions:
        m["frames"] = cfg.frames
    splits = split_table(identities, motions)
    pairs = sequences_for(identities, motions, splits)
    frames = [cfg.frames] * len(pairs)
    num_vertices = TOPOLOGIES[cfg.topology]
    seeds = {
        "seed": cfg.seed,
        "identities": identity_seed,
        "drivers": derive_seed(cfg.seed, "drivers"),
        "unseen": derive_seed(cfg.seed, "unseen"),
        "motions": "per motion, see motions[].seed",
        "pairs": "derive_seed(seed, 'pairs', split, epoch)",
    }
    return new_manifest(
        kind="synthetic",
        topology=cfg.topology,
        num_vertices=num_vertices,
        identities=identities,
        motions=motions,
        sequences=pairs,
        frames=frames,
        splits=splits,
        seeds=seeds,
        config={k: v for k, v in cfg.to_dict().items() if k not in EXECUTION_FIELDS},
    )


def shard_layout(manifest: Manifest, shard_mb: float, min_shards: int = 16) -> list[list[int]]:
    """Sequence ids per shard: consecutive, at most ``shard_mb`` MB of vertices per shard, and at
    least ``min_shards`` shards when there are that many sequences (parallelism for generation).
    A function of the manifest only, never of the number of workers."""
    frames = manifest.sequences["frames"]
    n = len(frames)
    if n == 0:
        return []
    mesh_bytes = manifest.num_vertices * 12
    by_size = max(1, int(shard_mb * 1e6 // (max(frames) * mesh_bytes)))
    per_shard = max(1, min(by_size, math.ceil(n / min_shards)))
    return [list(range(s, min(n, s + per_shard))) for s in range(0, n, per_shard)]

