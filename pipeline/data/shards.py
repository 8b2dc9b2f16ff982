"""The Parquet codec of bank shards: one row per mesh (sequence, identity, motion, frame, vertices),
written without timestamps so the same meshes give the same bytes; reading checks digests and layout."""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from aniformer.errors import UserError
from pipeline.data.manifest import SCHEMA_VERSION, Manifest


def _vertices_type(num_vertices: int):
    return pa.list_(pa.float32(), num_vertices * 3)


def shard_schema(num_vertices: int):
    return pa.schema(
        [
            ("sequence", pa.int32()),
            ("identity", pa.int32()),
            ("motion", pa.int32()),
            ("frame", pa.int32()),
            ("vertices", _vertices_type(num_vertices)),
        ],
        metadata={
            "aniformer.schema_version": str(SCHEMA_VERSION),
            "aniformer.vertices": "(V, 3) float32 metres, z up",
        },
    )


def shard_bytes(sequence_ids: Sequence[int], manifest: Manifest, vertices: Sequence[np.ndarray]) -> bytes:
    """Parquet bytes of one shard: ``vertices[k]`` is ``(frames, V, 3)`` of ``sequence_ids[k]``."""
    seqs = manifest.sequences
    V = manifest.num_vertices
    cols = {"sequence": [], "identity": [], "motion": [], "frame": []}
    for s, verts in zip(sequence_ids, vertices, strict=True):
        f = len(verts)
        if verts.shape != (seqs["frames"][s], V, 3):
            raise ValueError(f"sequence {s}: vertices {verts.shape}, expected {(seqs['frames'][s], V, 3)}")
        cols["sequence"].append(np.full(f, s, np.int32))
        cols["identity"].append(np.full(f, seqs["identity"][s], np.int32))
        cols["motion"].append(np.full(f, seqs["motion"][s], np.int32))
        cols["frame"].append(np.arange(f, dtype=np.int32))
    flat = np.ascontiguousarray(np.concatenate([np.asarray(v, np.float32).reshape(-1) for v in vertices]))
    arrays = [pa.array(np.concatenate(cols[k])) for k in ("sequence", "identity", "motion", "frame")]
    arrays.append(pa.FixedSizeListArray.from_arrays(pa.array(flat), V * 3))
    table = pa.Table.from_arrays(arrays, schema=shard_schema(V))
    sink = pa.BufferOutputStream()
    pq.write_table(
        table,
        sink,
        compression="zstd",
        use_dictionary=False,
        use_byte_stream_split=["vertices"],
        row_group_size=max(1, min(len(table), int(64e6 // (V * 12)))),
        write_statistics=False,
    )
    return sink.getvalue().to_pybytes()


def read_file(path: Path, what: str) -> bytes:
    """The bytes of a bank file; `UserError` naming it if missing or unreadable."""
    if not path.is_file():
        raise UserError(f"{path}: {what} missing from the bank")
    try:
        return path.read_bytes()
    except OSError as e:
        raise UserError(f"{path}: unreadable {what} ({e.strerror})") from None


def check_digest(path: Path, payload: bytes, sha256: str, size: int | None) -> None:
    """`UserError` naming the file unless ``payload`` has the manifest's SHA-256."""
    if hashlib.sha256(payload).hexdigest() != sha256:
        sizes = f"; {len(payload):,} bytes, the manifest says {size:,}" if size not in (None, len(payload)) else ""
        raise UserError(f"{path}: SHA-256 differs from the manifest (corrupt, truncated or modified{sizes}); "
                        "regenerate the bank or restore the file")


def read_shard(path: Path, payload: bytes, shard: dict, num_vertices: int):
    """The Parquet table of one shard's bytes, its layout checked against the manifest."""
    try:
        table = pq.read_table(pa.BufferReader(payload), columns=["sequence", "identity", "motion", "frame", "vertices"])
    except (pa.ArrowException, OSError, ValueError, KeyError) as e:
        first = (str(e).splitlines() or [type(e).__name__])[0]
        raise UserError(f"{path}: unreadable shard ({type(e).__name__}: {first[:200]}); regenerate the bank") from None
    kind = table.schema.field("vertices").type
    if not pa.types.is_fixed_size_list(kind) or kind.value_type != pa.float32():
        raise UserError(f"{path}: vertices column is {kind}, expected fixed_size_list<float32>")
    if kind.list_size != num_vertices * 3:
        raise UserError(f"{path}: holds meshes of {kind.list_size // 3} vertices ({kind.list_size} values), "
                        f"the manifest says num_vertices {num_vertices}")
    if table.num_rows != shard["rows"]:
        raise UserError(f"{path}: {table.num_rows} rows, manifest says {shard['rows']}")
    return table

