"""Training data: pairs made on the fly, or a mesh bank in Parquet shards, and pairs per epoch with Ray Data.

One module per step: ``config`` (the ``data:`` section, splits, seeds), ``plan`` (identities, motions,
sequences, shard layout), ``manifest`` (the bank's layout on disk and its checks), ``shards`` (the Parquet
codec), ``synthetic`` (posing Anny bodies), ``importer`` (mesh folders -> bank), ``bank`` (loading),
``pairs`` (numpy pairs) and ``ray_data`` (generation and pair datasets on Ray). This package exports
what the jobs and the trainer use.

A run's pairs come from ``pair_source(cfg, bank)``, the one place that chooses where they come from, as
a ``PairSource`` (its splits and their descriptions, ``non_empty_splits``, ``batch``, ``faces``,
``num_vertices``): with ``data.source: stream`` (the default configs) every pair is made on the fly by
``aniformer.synth.stream.StreamPairs`` inside the Ray Data tasks (fresh bodies, smooth motion over the
whole pose space; no bank, nothing on disk; splits ``STREAM_SPLITS``); with ``data.source: bank`` they
are assembled from a mesh bank, the format below, which also holds imported mesh sequences
(DFAUST-like data, ``import_mesh_sequences``).

The mesh bank
-------------
Following the paper's DFAUST setup, a *motion instance* (one clip: an action performed with its
own amplitude, tempo and noise) is performed by exactly one *driving identity*; the ground truth
of a pair is a *target identity* performing that same clip. So the bank stores one 30-frame
vertex sequence per (identity, motion instance) that any pair can need:

- each driving identity performing its own motion instances (the driving sequences);
- every train target performing every *seen* motion instance (training ground truth and target
  poses); every test target performing every motion instance (evaluation).

On disk (``DIR/``)::

    manifest.json               schema version, topology, counts, identities, motions, sequences,
                                splits, seeds, the data config, shard list with SHA-256 digests
    faces.npy                   (F, 3) int64, shared by every mesh of the bank
    shards/part-00000.parquet   one row per mesh: sequence, identity, motion, frame (int32),
                                vertices fixed_size_list<float32>[V*3] (metres, z up, not centred)

Rows are in global order (sequence-major, frames ascending); ``manifest.sequences["first_row"]``
locates a sequence. Generation is a Ray Data pipeline (one work unit per shard, an actor pool
that keeps one Anny body model per worker) and is deterministic regardless of the number of
workers: every shard is a pure function of (config, shard index), torch runs single-threaded, and
the Parquet bytes are written without timestamps under fixed names.

Pairs
-----
``PairSampler`` (numpy only, no Ray) turns the bank into training/evaluation pairs:
(driving motion instance, start frame, window T) x target identity -> ``driving (T, V, 3)``,
``target (V, 3)`` (the target identity at a random frame of a random motion of the split, as in
the paper), ``ground_truth (T, V, 3)`` (the target performing the driving window) and
``target_faces (F, 3)``. Pair ``i`` of epoch ``e`` of a split is a pure function of
(seed, split, e, i). Every mesh is bounding-box centred (``center``). Vertex shuffling: ``none``;
``target`` (target and ground truth share one permutation, the driver keeps the bank order);
``both`` (the driver gets its own permutation too). ``pair_dataset`` wraps the sampler in Ray Data
for Ray Train (``ray.train.get_dataset_shard("train").iter_torch_batches(...)``).

Splits (the paper's, plus harder ones): driving identities seen/unseen, motion instances
seen/unseen, target identities train/test, and held-out action classes; see ``BANK_SPLITS``.
"""

from pipeline.data.bank import Bank, check_bank_matches, load_bank, read_faces
from pipeline.data.config import BANK_SPLITS, GENERATION_FIELDS, DataConfig, data_config, derive_seed
from pipeline.data.importer import import_mesh_sequences
from pipeline.data.manifest import MANIFEST, SCHEMA_VERSION, Manifest, read_manifest, validate_manifest
from pipeline.data.pairs import PairSampler, PairSource, pair_source
from pipeline.data.plan import plan_bank, shard_layout
from pipeline.data.ray_data import generate_bank, pair_dataset, prepare_bank, quiet_ray_data
from pipeline.data.shards import shard_bytes
from pipeline.data.synthetic import generate_shard, motion_of, pose_sequence

__all__ = [
    "BANK_SPLITS", "GENERATION_FIELDS", "MANIFEST", "SCHEMA_VERSION", "Bank", "DataConfig", "Manifest", "PairSampler",
    "PairSource", "check_bank_matches", "data_config", "derive_seed", "generate_bank", "generate_shard",
    "import_mesh_sequences", "load_bank", "motion_of", "pair_dataset", "pair_source", "plan_bank", "pose_sequence",
    "prepare_bank", "quiet_ray_data", "read_faces", "read_manifest", "shard_bytes", "shard_layout", "validate_manifest",
]
