"""The bank's manifest (`Manifest`): its layout on disk, its schema check, and the files it names.

A bank directory holds ``manifest.json``, ``faces.npy`` and ``shards/part-NNNNN.parquet``; the manifest is
written last, so a bank with a manifest is complete. Every path a manifest names is checked to stay
inside the bank (`bank_file`). `read_manifest` checks the JSON (`validate_manifest`) before it becomes a
`Manifest`, whose records (identities, motions, splits, shards) stay the JSON objects the file holds.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import os
import re
from pathlib import Path

import numpy as np

from aniformer.errors import UserError
from aniformer.io.files import atomic_path

SCHEMA_VERSION = 1
MANIFEST = "manifest.json"
FACES = "faces.npy"
SHARD_DIR = "shards"


@dataclasses.dataclass(frozen=True)
class Manifest:
    """What a bank holds and where (``manifest.json``, schema `SCHEMA_VERSION`). Made by `new_manifest`
    (no shards yet), completed by `finish_bank`, read back by `read_manifest`."""

    kind: str  # "synthetic" (from a data config) or "meshes" (imported mesh folders)
    topology: str
    num_vertices: int
    faces: str  # the faces file, relative to the bank
    counts: dict  # identities, drivers/targets by split, motions by group, sequences, meshes, shards, faces
    identities: list  # {id, name, role, split, phenotype?}
    motions: list  # {id, name, driver, frames, split, action?, instance?, seed?}
    sequences: dict  # columns identity, motion, frames, first_row: the rows of (identity, motion) in order
    splits: dict  # name -> {motions, targets, description}
    seeds: dict = dataclasses.field(default_factory=dict)
    config: dict = dataclasses.field(default_factory=dict)  # a synthetic bank's generation config, an import's options
    shards: list = dataclasses.field(default_factory=list)  # {path, rows, sequences, first_row, bytes, sha256}
    faces_sha256: str | None = None  # None: a bank from before faces had a digest
    schema_version: int = SCHEMA_VERSION

    def to_json(self) -> dict:
        return {k: v for k, v in dataclasses.asdict(self).items() if v is not None}


def new_manifest(*, kind, topology, num_vertices, identities, motions, sequences, frames, splits, seeds,
                 config) -> Manifest:
    """The manifest of a bank about to be written, minus its shards (``sequences`` are (identity, motion))."""
    first_row = np.concatenate([[0], np.cumsum(frames)[:-1]]).astype(int).tolist() if frames else []
    roles = [i["role"] + "_" + i["split"] for i in identities]
    return Manifest(
        kind=kind,
        topology=topology,
        num_vertices=int(num_vertices),
        faces=FACES,
        counts={
            "identities": len(identities),
            "drivers_seen": roles.count("driver_seen"),
            "drivers_unseen": roles.count("driver_unseen"),
            "targets_train": roles.count("target_train"),
            "targets_test": roles.count("target_test"),
            "motions": len(motions),
            **{f"motions_{g}": sum(m["split"] == g for m in motions) for g in ("seen", "unseen", "unseen_driver", "heldout")},
            "sequences": len(sequences),
            "meshes": int(sum(frames)),
        },
        identities=identities,
        motions=motions,
        sequences={
            "identity": [int(i) for i, _ in sequences],
            "motion": [int(m) for _, m in sequences],
            "frames": [int(f) for f in frames],
            "first_row": first_row,
        },
        splits=splits,
        seeds=seeds,
        config=config,
    )


def write_file(path: Path, payload: bytes) -> None:
    """Write bytes under a temporary name, then rename into place."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(payload)


def write_json(path: Path, obj: dict) -> None:
    write_file(path, (json.dumps(obj, indent=1, sort_keys=True) + "\n").encode())


def npy_bytes(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=False)
    return buf.getvalue()


def shard_name(index: int) -> str:
    return f"{SHARD_DIR}/part-{index:05d}.parquet"


def finish_bank(out_dir: Path, manifest: Manifest, faces: np.ndarray, shards: list[dict]) -> Manifest:
    """Write the faces and, last, the manifest with its shard list and digests; returns the manifest."""
    faces_bytes = npy_bytes(np.asarray(faces, np.int64))
    manifest = dataclasses.replace(manifest, shards=sorted(shards, key=lambda s: s["path"]),
                                   counts=dict(manifest.counts, shards=len(shards), faces=int(len(faces))),
                                   faces_sha256=hashlib.sha256(faces_bytes).hexdigest())
    write_file(out_dir / FACES, faces_bytes)
    write_json(out_dir / MANIFEST, manifest.to_json())  # last: a bank with a manifest is complete
    return manifest


def read_manifest(bank_dir: str | os.PathLike) -> Manifest:
    """The manifest of a bank directory, its schema checked (`validate_manifest`); `UserError` with one
    line naming the file if it is missing, unreadable, incompatible or inconsistent."""
    path = Path(bank_dir) / MANIFEST
    if not path.is_file():
        raise UserError(f"{bank_dir}: not a mesh bank (no {MANIFEST}); make one with jobs/generate_data.py")
    try:
        manifest = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise UserError(f"{path}: unreadable manifest ({e})") from None
    if not isinstance(manifest, dict):
        raise UserError(f"{path}: not a bank manifest (a JSON {type(manifest).__name__}, not an object)")
    if manifest.get("schema_version") != SCHEMA_VERSION:
        raise UserError(
            f"{path}: schema version {manifest.get('schema_version')!r}, this code reads {SCHEMA_VERSION}; regenerate the bank"
        )
    validate_manifest(manifest, path)
    return Manifest(**manifest)


REQUIRED_KEYS = {"kind": str, "topology": str, "num_vertices": int, "faces": str, "counts": dict, "identities": list,
             "motions": list, "sequences": dict, "splits": dict, "shards": list}
OPTIONAL_KEYS = {"seeds": dict, "config": dict, "faces_sha256": str, "schema_version": int}
_SHA256 = re.compile(r"[0-9a-f]{64}")


def _is_int(value, low: int = 0) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= low


def _refuse(path, problem: str):
    raise UserError(f"{path}: {problem}; regenerate the bank (or restore its manifest)")


def validate_manifest(manifest: dict, path: str | os.PathLike = MANIFEST) -> None:
    """`UserError` (one line naming `path`) unless the manifest is one this code can read safely: every
    key present with its type, ids in range, the sequences' rows consecutive and the shards covering
    them exactly, each shard with a SHA-256, file paths inside the bank. The shards themselves are
    checked against it as they are read (`load_bank`)."""
    missing = [k for k in REQUIRED_KEYS if k not in manifest]
    if missing:
        _refuse(path, f"missing key(s) {', '.join(missing)}")
    unknown = sorted(set(manifest) - set(REQUIRED_KEYS) - set(OPTIONAL_KEYS))
    if unknown:
        _refuse(path, f"unknown key(s) {', '.join(unknown)}")
    types = {**REQUIRED_KEYS, **OPTIONAL_KEYS}
    wrong = [f"{k} ({type(manifest[k]).__name__}, not {t.__name__})" for k, t in types.items()
             if k in manifest and (not isinstance(manifest[k], t) or (t is int and isinstance(manifest[k], bool)))]
    if wrong:
        _refuse(path, f"wrong type of {', '.join(wrong)}")
    if manifest["num_vertices"] < 3:
        _refuse(path, f"num_vertices {manifest['num_vertices']} < 3")
    if manifest["kind"] == "synthetic" and not manifest.get("config"):
        _refuse(path, "a synthetic bank without its config")
    _check_records(manifest, path)
    rows = _check_sequences(manifest, path)
    _check_splits(manifest, path)
    _check_shards(manifest, path, rows)
    bank_file(Path(path).parent, manifest["faces"], "faces")
    if "faces_sha256" in manifest and not _SHA256.fullmatch(manifest["faces_sha256"]):
        _refuse(path, "faces_sha256 is not a SHA-256 digest")


def _check_records(manifest: dict, path) -> None:
    identities, motions = manifest["identities"], manifest["motions"]
    n_ident = len(identities)
    for i, ident in enumerate(identities):
        if not isinstance(ident, dict) or ident.get("id") != i or not isinstance(ident.get("name"), str):
            _refuse(path, f"identities[{i}] is not {{id: {i}, name: ...}}")
    for i, motion in enumerate(motions):
        if (not isinstance(motion, dict) or motion.get("id") != i or not isinstance(motion.get("name"), str)
                or not _is_int(motion.get("driver")) or motion["driver"] >= n_ident
                or not _is_int(motion.get("frames"), 1)):
            _refuse(path, f"motions[{i}] is not {{id: {i}, name, driver < {n_ident}, frames >= 1}}")


def _check_sequences(manifest: dict, path) -> int:
    """The sequence table's consistency; returns its number of rows (meshes)."""
    n_ident, n_motion, motions = len(manifest["identities"]), len(manifest["motions"]), manifest["motions"]
    seqs = manifest["sequences"]
    columns = ("identity", "motion", "frames", "first_row")
    if any(not isinstance(seqs.get(c), list) for c in columns) or len({len(seqs[c]) for c in columns}) != 1:
        _refuse(path, f"sequences must hold lists {', '.join(columns)} of one length")
    if not all(all(_is_int(v) for v in seqs[c]) for c in columns):
        _refuse(path, "sequences hold a value that is not a non-negative integer")
    if any(i >= n_ident for i in seqs["identity"]) or any(m >= n_motion for m in seqs["motion"]):
        _refuse(path, f"a sequence names an identity >= {n_ident} or a motion >= {n_motion}")
    if any(f != motions[m]["frames"] for f, m in zip(seqs["frames"], seqs["motion"], strict=True)):
        _refuse(path, "a sequence's frame count differs from its motion's")
    if len(set(zip(seqs["identity"], seqs["motion"], strict=True))) != len(seqs["identity"]):
        _refuse(path, "two sequences of one identity and motion")
    rows = int(sum(seqs["frames"]))
    expected_first = np.concatenate([[0], np.cumsum(seqs["frames"])[:-1]]).astype(int).tolist() if rows else []
    if seqs["first_row"] != expected_first:
        _refuse(path, "sequences.first_row is not the running sum of sequences.frames")
    meshes = manifest["counts"].get("meshes")
    if meshes != rows:
        _refuse(path, f"counts.meshes is {meshes!r} but the sequences hold {rows} frames")
    return rows


def _check_splits(manifest: dict, path) -> None:
    n_ident, n_motion = len(manifest["identities"]), len(manifest["motions"])
    for name, split in manifest["splits"].items():
        if (not isinstance(split, dict) or not isinstance(split.get("motions"), list)
                or not isinstance(split.get("targets"), list)
                or not all(_is_int(m) and m < n_motion for m in split["motions"])
                or not all(_is_int(t) and t < n_ident for t in split["targets"])):
            _refuse(path, f"split {name!r} is not {{motions: [ids < {n_motion}], targets: [ids < {n_ident}]}}")


def _check_shards(manifest: dict, path, rows: int) -> None:
    covered = 0
    for k, shard in enumerate(sorted(manifest["shards"], key=lambda sh: sh.get("first_row", -1)
                                     if isinstance(sh, dict) else -1)):
        if (not isinstance(shard, dict) or not isinstance(shard.get("path"), str)
                or not _is_int(shard.get("rows"), 1) or not _is_int(shard.get("first_row"))
                or not _is_int(shard.get("bytes"), 1)):
            _refuse(path, f"shard {k} is not {{path, rows >= 1, first_row, bytes, sha256}}")
        if not isinstance(shard.get("sha256"), str) or not _SHA256.fullmatch(shard["sha256"]):
            _refuse(path, f"shard {shard['path']} has no SHA-256 digest")
        if shard["first_row"] != covered:
            _refuse(path, f"shard {shard['path']} starts at row {shard['first_row']}, expected {covered}")
        covered += shard["rows"]
        bank_file(Path(path).parent, shard["path"], "shard")
    if covered != rows:
        _refuse(path, f"the shards hold {covered} rows but the sequences {rows}")


def bank_file(bank_dir: str | os.PathLike, relative: str, what: str) -> Path:
    """`bank_dir / relative`, refused in one line if it leads outside the bank (an absolute path, a
    `..` component, or a symlink out): a manifest must not make a job read or overwrite other files."""
    bank_dir = Path(bank_dir)
    parts = Path(relative).parts
    path = bank_dir / relative
    if (not relative or os.path.isabs(relative) or ".." in parts or "\0" in relative
            or not path.resolve().is_relative_to(bank_dir.resolve())):
        raise UserError(f"{bank_dir / MANIFEST}: {what} path {relative!r} leads outside the bank; refused")
    return path

