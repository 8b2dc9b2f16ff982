"""Nothing lost, nothing silently wrong (issue 18): bank integrity.

No Ray: banks are written here from random vertices with the bank's own writers, jobs are run only
up to the point where they refuse (before Ray starts). Concurrency uses real second processes.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from aniformer.cli import UserError, load_config, run
from pipeline import data

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "configs" / "tiny.yaml"


def make_bank(root: Path) -> Path:
    """The tiny config's bank plan with random vertices, written by the bank's own shard writer."""
    cfg = data.data_config(load_config(TINY))
    manifest = data.plan_bank(cfg)
    V = manifest["num_vertices"]
    rng = np.random.default_rng(0)
    shards = []
    for i, seqs in enumerate(data.shard_layout(manifest, cfg.shard_mb)):
        verts = [rng.standard_normal((manifest["sequences"]["frames"][s], V, 3)).astype(np.float32) for s in seqs]
        payload = data.shard_bytes(seqs, manifest, verts)
        path = data._shard_name(i)
        data._write_file(root / path, payload)
        shards.append({"path": path, "rows": sum(len(v) for v in verts), "sequences": [seqs[0], seqs[-1] + 1],
                       "first_row": manifest["sequences"]["first_row"][seqs[0]], "bytes": len(payload),
                       "sha256": hashlib.sha256(payload).hexdigest()})
    faces = np.stack([np.arange(V), (np.arange(V) + 1) % V, (np.arange(V) + 2) % V], 1)
    data._finish_bank(root, manifest, faces, shards)
    return root


@pytest.fixture(scope="module")
def pristine(tmp_path_factory) -> Path:
    return make_bank(tmp_path_factory.mktemp("integrity") / "bank")


@pytest.fixture
def bank(pristine, tmp_path) -> Path:
    """A fresh copy of the bank for a test to damage."""
    return Path(shutil.copytree(pristine, tmp_path / "bank"))


def manifest_of(bank: Path) -> dict:
    return json.loads((bank / data.MANIFEST).read_text())


def edit_manifest(bank: Path, change) -> None:
    manifest = manifest_of(bank)
    change(manifest)  # in place
    (bank / data.MANIFEST).write_text(json.dumps(manifest))


def refusal(call) -> str:
    with pytest.raises(UserError) as e:
        call()
    message = str(e.value)
    assert "\n" not in message and "Traceback" not in message, message
    return message


# ------------------------------------------------------------------------------ bank integrity


def test_intact_bank_loads_verified_by_default(bank):
    loaded = data.load_bank(bank)
    assert loaded.vertices.shape == (manifest_of(bank)["counts"]["meshes"], 369, 3)
    assert "faces_sha256" in manifest_of(bank)


def test_a_flipped_byte_anywhere_in_a_shard_is_refused_naming_the_shard(bank):
    shard = bank / manifest_of(bank)["shards"][3]["path"]
    original = shard.read_bytes()
    rng = np.random.default_rng(18)
    for position in rng.integers(0, len(original), size=40):
        damaged = bytearray(original)
        damaged[position] ^= 1 << int(rng.integers(8))
        shard.write_bytes(bytes(damaged))
        message = refusal(lambda: data.load_bank(bank))
        assert str(shard) in message and "SHA-256" in message, (position, message)
    shard.write_bytes(original)
    data.load_bank(bank)


def test_a_truncated_shard_is_one_line_naming_the_file(bank):
    shard = bank / manifest_of(bank)["shards"][0]["path"]
    payload = shard.read_bytes()
    shard.write_bytes(payload[: len(payload) // 2])
    message = refusal(lambda: data.load_bank(bank))
    assert str(shard) in message and "truncated" in message and f"{len(payload):,}" in message
    message = refusal(lambda: data.load_bank(bank, verify=False))  # the Parquet reader's error, one line
    assert str(shard) in message and "unreadable shard" in message


def test_num_vertices_edited_in_the_manifest_is_refused(bank):
    edit_manifest(bank, lambda m: m.update(num_vertices=370))
    message = refusal(lambda: data.load_bank(bank))
    assert "369 vertices" in message and "num_vertices 370" in message and "part-" in message


def test_rows_moved_in_the_manifest_are_refused(bank):
    """Sequence 0 and 1 swapped in the manifest (frames and shards unchanged): every row would be read
    as another identity's mesh."""
    def swap(m):
        for key in ("identity", "motion"):
            seq = m["sequences"][key]
            seq[0], seq[1] = seq[1], seq[0]
    edit_manifest(bank, swap)
    message = refusal(lambda: data.load_bank(bank))
    assert "part-00000" in message and "not the sequences and frames" in message


@pytest.mark.parametrize("content, words", [
    ([], "a JSON list, not an object"),
    ("bank", "a JSON str"),
    ({"schema_version": 1}, "missing key(s) kind, topology, num_vertices, faces"),
])
def test_manifest_that_is_not_a_bank_manifest_is_one_line(bank, content, words):
    (bank / data.MANIFEST).write_text(json.dumps(content))
    message = refusal(lambda: data.read_manifest(bank))
    assert str(bank / data.MANIFEST) in message and words in message, message


@pytest.mark.parametrize("key", sorted(data._REQUIRED))
def test_each_missing_manifest_key_is_named(bank, key):
    edit_manifest(bank, lambda m: m.pop(key))
    message = refusal(lambda: data.load_bank(bank))
    assert f"missing key(s) {key}" in message and "regenerate" in message


@pytest.mark.parametrize("change, words", [
    (lambda m: m.update(num_vertices="369"), "num_vertices (str, not int)"),
    (lambda m: m["counts"].update(meshes=901), "counts.meshes is 901"),
    (lambda m: m["sequences"]["first_row"].__setitem__(1, 31), "first_row"),
    (lambda m: m["sequences"]["frames"].pop(), "lists identity, motion, frames, first_row of one length"),
    (lambda m: m["sequences"]["identity"].__setitem__(0, 99), "identity >= 7"),
    (lambda m: m["motions"][0].update(driver=50), "motions[0]"),
    (lambda m: m["splits"]["train"]["targets"].append(12), "split 'train'"),
    (lambda m: m["shards"].pop(), "the shards hold"),
    (lambda m: m["shards"][0].update(first_row=5), "starts at row 5"),
    (lambda m: m["shards"][2].pop("sha256"), "has no SHA-256 digest"),
    (lambda m: m.pop("config"), "without its config"),
])
def test_inconsistent_manifest_is_refused_before_any_shard_is_read(bank, change, words):
    edit_manifest(bank, change)
    message = refusal(lambda: data.read_manifest(bank))
    assert words in message and str(bank / data.MANIFEST) in message, message


@pytest.mark.parametrize("key", ["faces", "shard"])
@pytest.mark.parametrize("path", ["../../../../etc/passwd", "/etc/passwd", "shards/../../outside.parquet"])
def test_paths_outside_the_bank_are_refused(bank, key, path):
    (bank.parent / "outside.parquet").write_bytes((bank / "shards/part-00000.parquet").read_bytes())
    edit_manifest(bank, lambda m: m.update(faces=path) if key == "faces" else m["shards"][0].update(path=path))
    message = refusal(lambda: data.load_bank(bank))
    assert "leads outside the bank" in message and repr(path) in message


def test_a_symlink_out_of_the_bank_is_refused(bank, tmp_path):
    outside = tmp_path / "faces.npy"
    shutil.move(bank / "faces.npy", outside)
    (bank / "faces.npy").symlink_to(outside)
    assert "leads outside the bank" in refusal(lambda: data.load_bank(bank))


def test_missing_or_damaged_faces(bank):
    faces = bank / "faces.npy"
    original = faces.read_bytes()
    faces.unlink()
    assert f"{faces}: faces file missing" in refusal(lambda: data.load_bank(bank))
    np.save(faces, np.zeros((4, 3), np.int64) + 400)  # valid .npy, indices out of range, digest differs
    assert "SHA-256 differs" in refusal(lambda: data.load_bank(bank))
    edit_manifest(bank, lambda m: m.pop("faces_sha256"))  # a bank from before the digest: the range check
    assert "indices in [0, 369)" in refusal(lambda: data.load_bank(bank))
    faces.write_bytes(original[:40])
    assert "not a readable .npy" in refusal(lambda: data.load_bank(bank))


def test_a_bank_written_before_faces_had_a_digest_still_loads(bank):
    """Banks made before this change record each shard's SHA-256 (always did) but not the faces'."""
    edit_manifest(bank, lambda m: m.pop("faces_sha256"))
    data.load_bank(bank)


def test_export_meshes_job_refuses_a_corrupt_bank_in_one_line(bank, tmp_path, capsys, job_main):
    shard = bank / "shards/part-00001.parquet"
    payload = bytearray(shard.read_bytes())
    payload[len(payload) // 2] ^= 0xFF
    shard.write_bytes(bytes(payload))
    with pytest.raises(SystemExit) as exit_:
        run(job_main("export_meshes"), ["--bank", str(bank), "--out", str(tmp_path / "x")])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.count("\n") == 1 and str(shard) in err, err
    assert not (tmp_path / "x").exists()
