"""Nothing lost, nothing silently wrong (issue 18): bank integrity, one job per output, `--overwrite`
that never deletes an input, MLflow run identity and a safely created store, SIGTERM.

No Ray: banks are written here from random vertices with the bank's own writers, jobs are run only
up to the point where they refuse (before Ray starts). Concurrency uses real second processes.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from aniformer.cli.args import load_config
from aniformer.cli.exits import run
from aniformer.errors import UserError
from pipeline import data
from pipeline.data import manifest as bank_manifest
from pipeline.data import ray_data

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "configs" / "tiny.yaml"
PY = sys.executable


def make_bank(root: Path) -> Path:
    """The tiny config's bank plan with random vertices, written by the bank's own shard writer."""
    cfg = data.data_config(load_config(TINY))
    manifest = data.plan_bank(cfg)
    V = manifest.num_vertices
    rng = np.random.default_rng(0)
    shards = []
    for i, seqs in enumerate(data.shard_layout(manifest, cfg.shard_mb)):
        verts = [rng.standard_normal((manifest.sequences["frames"][s], V, 3)).astype(np.float32) for s in seqs]
        payload = data.shard_bytes(seqs, manifest, verts)
        path = bank_manifest.shard_name(i)
        bank_manifest.write_file(root / path, payload)
        shards.append({"path": path, "rows": sum(len(v) for v in verts), "sequences": [seqs[0], seqs[-1] + 1],
                       "first_row": manifest.sequences["first_row"][seqs[0]], "bytes": len(payload),
                       "sha256": hashlib.sha256(payload).hexdigest()})
    faces = np.stack([np.arange(V), (np.arange(V) + 1) % V, (np.arange(V) + 2) % V], 1)
    bank_manifest.finish_bank(root, manifest, faces, shards)
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


@pytest.mark.parametrize("key", sorted(bank_manifest.REQUIRED_KEYS))
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
    (lambda m: m.update(colour="red"), "unknown key(s) colour"),
    (lambda m: m.update(seeds=[1]), "seeds (list, not dict)"),
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


# ------------------------------------------------------------------------- one job per output

HOLDER = textwrap.dedent("""
    import sys, time
    from aniformer.cli.locks import lock_output
    lock_output(sys.argv[1])
    print("locked", flush=True)
    time.sleep(120)
""")


@pytest.fixture
def holder(tmp_path, read_line):
    """`holder(out)`: a second process that holds the lock on `out` until the test ends (or kills it)."""
    procs = []

    def start(out: Path) -> subprocess.Popen:
        proc = subprocess.Popen([PY, "-c", HOLDER, str(out)], stdout=subprocess.PIPE, text=True)
        procs.append(proc)
        assert read_line(proc.stdout, 60, "the lock holder").strip() == "locked"
        return proc

    yield start
    for proc in procs:
        proc.kill()
        proc.wait()


JOBS = {
    "train": ["--config", TINY],
    "sweep": ["--config", ROOT / "configs/sweep_tiny.yaml"],
    "ablate": ["--config", ROOT / "configs/ablation.yaml"],
    "generate_data": ["--config", TINY],
    "export_meshes": ["--stream", "notoes_collapse3pc"],
}


@pytest.mark.parametrize("job", sorted(JOBS))
def test_a_second_job_on_the_same_out_is_refused_naming_the_first(job, tmp_path, holder, capsys, job_main):
    out = tmp_path / "out"
    first = holder(out)
    with pytest.raises(SystemExit) as exit_:
        run(job_main(job), [*map(str, JOBS[job]), "--out", str(out)])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.count("\n") == 1, err
    assert f"--out {out} is in use by another job (pid {first.pid} on " in err and "-c " in err, err


def test_the_lock_is_released_when_the_holder_dies_and_its_file_removed_after_a_job(tmp_path, holder):
    from aniformer.cli.locks import LOCK_NAME, lock_output

    out = tmp_path / "out"
    first = holder(out)
    assert "in use" in refusal(lambda: lock_output(out))
    first.send_signal(signal.SIGKILL)
    first.wait()
    assert (out / LOCK_NAME).exists()  # a killed holder leaves the file, not the lock
    run(lambda _: lock_output(out), [])  # a job: takes the lock, ends
    assert not (out / LOCK_NAME).exists() and out.is_dir()


def test_a_job_main_called_directly_releases_its_lock_and_leaves_no_directory(tmp_path, job_main):
    """Not through `cli.run` (tests call the mains directly): a UserError after the lock was taken still
    releases it, and removes the `--out` it created to hold it."""
    from aniformer.cli.locks import _HELD

    out = tmp_path / "x"
    with pytest.raises(UserError, match="not a split of the stream"):
        job_main("export_meshes")(["--stream", "notoes_collapse3pc", "--split", "nope", "--out", str(out)])
    assert not out.exists() and not _HELD


def test_a_staged_output_stays_locked_while_it_replaces_the_old_one(tmp_path, holder):
    """The staging directory is locked before it is swapped in, so no other job gets in between."""
    from aniformer.cli.locks import release_locks
    from aniformer.cli.outputs import claim_output, staged_output_dir

    out = tmp_path / "out"
    out.mkdir()
    (out / "old.txt").write_text("old")
    probe = [PY, "-c", f"from aniformer.cli.locks import lock_output; lock_output({str(out)!r})"]
    try:
        claim_output(out, overwrite=True)
        with staged_output_dir(out, overwrite=True) as tmp:
            (tmp / "new.txt").write_text("new")
        assert sorted(p.name for p in out.iterdir()) == [".lock", "new.txt"]
        second = subprocess.run(probe, capture_output=True, text=True)
        assert second.returncode != 0 and "in use by another job" in second.stderr
    finally:
        release_locks()
    assert sorted(p.name for p in out.iterdir()) == ["new.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no staging, no old directory left
    assert subprocess.run(probe).returncode == 0


def test_stale_staging_directories_are_removed_at_the_next_start(tmp_path, holder):
    from aniformer.cli.locks import release_locks
    from aniformer.cli.outputs import claim_output, staged_output_dir

    out = tmp_path / "out"
    dead = subprocess.run([PY, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    live = holder(tmp_path / "elsewhere")
    for name in (f".out.{dead.stdout.strip()}-abcdefgh.tmp", f".out.{live.pid}-ijklmnop.tmp", ".out.qrstuvwx.tmp"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "shard").write_text("partial")
    (tmp_path / ".outer.abcdefgh.tmp").mkdir()  # another output's: never touched
    with staged_output_dir(out, overwrite=False) as tmp:  # unlocked: only a dead process's leftovers go
        (tmp / "a").write_text("a")
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left == sorted([".out.qrstuvwx.tmp", f".out.{live.pid}-ijklmnop.tmp", ".outer.abcdefgh.tmp", "elsewhere",
                           "out"])
    try:
        claim_output(out, overwrite=True)  # locked: nobody else can be staging this output
        with staged_output_dir(out, overwrite=True) as tmp:
            (tmp / "b").write_text("b")
    finally:
        release_locks()
    assert sorted(p.name for p in tmp_path.iterdir()) == [".outer.abcdefgh.tmp", "elsewhere", "out"]


def test_an_incomplete_own_bank_is_regenerated_staged(tmp_path, monkeypatch):
    """What an unstaged generation killed mid-way left (shards, no manifest) is replaced; a killed
    staged one left a staging directory, which the next start removes."""
    from aniformer.cli.locks import lock_output, release_locks

    out = tmp_path / "run"
    bank = out / "bank"
    (bank / "shards").mkdir(parents=True)
    (bank / "shards/part-00000.parquet").write_bytes(b"partial")
    (out / ".bank.1-abcdefgh.tmp").mkdir()
    calls = []

    def fake_generate(cfg, where, **_):
        calls.append(Path(where))
        assert Path(where).parent == out and not bank.joinpath(data.MANIFEST).exists()
        return make_bank(Path(where)) and data.read_manifest(where)

    monkeypatch.setattr(ray_data, "generate_bank", fake_generate)
    cfg = data.data_config(load_config(TINY))
    try:
        lock_output(out)
        manifest, faces = data.prepare_bank(cfg, bank, generate=True)
    finally:
        release_locks()
    assert len(calls) == 1 and (bank / data.MANIFEST).is_file() and faces.shape[1] == 3
    assert sorted(p.name for p in out.iterdir()) == ["bank"]
    (tmp_path / "other" / "bank").mkdir(parents=True)
    (tmp_path / "other" / "bank" / "notes.txt").write_text("mine")
    assert "holds no mesh bank" in refusal(lambda: data.prepare_bank(cfg, tmp_path / "other" / "bank", generate=True))


# ---------------------------------------------------------------- --overwrite never deletes an input


def test_protect_inputs(tmp_path):
    from aniformer.cli.outputs import protect_inputs

    run_dir = tmp_path / "run"
    (run_dir / "bank").mkdir(parents=True)
    (run_dir / "best.pt").write_bytes(b"x")
    (tmp_path / "link").symlink_to(run_dir, target_is_directory=True)
    assert "is the input --bank" in refusal(lambda: protect_inputs(run_dir / "bank", {"--bank": run_dir / "bank"}))
    assert "contains the input --checkpoint" in refusal(
        lambda: protect_inputs(run_dir, {"--checkpoint": run_dir / "best.pt"}))
    assert "contains the input --checkpoint" in refusal(  # through a symlink
        lambda: protect_inputs(run_dir, {"--checkpoint": tmp_path / "link" / "best.pt"}))
    assert "is inside the input --driving" in refusal(
        lambda: protect_inputs(run_dir / "bank" / "anim", {"--driving": run_dir / "bank"}))
    protect_inputs(tmp_path / "elsewhere", {"--checkpoint": run_dir / "best.pt", "--bank": run_dir / "bank"})
    protect_inputs(run_dir, {"--checkpoint": "0123456789abcdef0123456789abcdef", "--bank": None})  # a run id
    (run_dir / "frames").mkdir()
    (run_dir / "frames" / "f0.obj").write_text("v 0 0 0")
    assert "contains the input --driving" in refusal(  # a glob: the files it matches
        lambda: protect_inputs(run_dir, {"--driving": str(run_dir / "frames" / "*.obj")}))
    protect_inputs(run_dir / "frames" / "anim", {"--driving": str(run_dir / "frames" / "*.obj")})
    assert "contains the input --compare" in refusal(  # a list: each of them
        lambda: protect_inputs(run_dir, {"--compare": ["0123456789abcdef0123456789abcdef", run_dir / "best.pt"]}))


def test_export_meshes_overwrite_never_deletes_its_bank(bank, capsys, job_main):
    before = {p: p.read_bytes() for p in bank.rglob("*") if p.is_file()}
    for out in (bank, bank.parent, bank / "samples"):
        with pytest.raises(SystemExit) as exit_:
            run(job_main("export_meshes"), ["--bank", str(bank), "--out", str(out), "--overwrite"])
        err = capsys.readouterr().err
        assert exit_.value.code == 2 and err.count("\n") == 1 and "input --bank" in err, err
    assert {p: p.read_bytes() for p in bank.rglob("*") if p.is_file()} == before
    assert not (bank / "samples").exists()


def test_generate_data_never_writes_into_its_sources(tmp_path, capsys, job_main):
    src = tmp_path / "meshes"
    (src / "a" / "clip").mkdir(parents=True)
    for out in (src, src / "bank", tmp_path):
        with pytest.raises(SystemExit) as exit_:
            run(job_main("generate_data"), ["--config", str(TINY), "--from-meshes", str(src), "--out", str(out),
                                            "--overwrite"])
        err = capsys.readouterr().err
        assert exit_.value.code == 2 and "input --from-meshes" in err, err
    assert sorted(p.name for p in src.rglob("*")) == ["a", "clip"]


# ------------------------------------------------------------------------------- MLflow runs


@pytest.fixture
def store(tmp_path, monkeypatch) -> str:
    from pipeline.tracking import quiet_mlflow

    quiet_mlflow()
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    return uri


def test_runs_are_identified_by_output_and_name(store, tmp_path):
    from pipeline.tracking import OUT_TAG, find_job_run, start_job_run

    a = start_job_run("tiny", {"train": {"lr": 1}}, out=tmp_path / "runs" / "tiny")
    b = start_job_run("tiny", {"train": {"lr": 2}}, out=tmp_path / "alt" / "tiny")  # same name, other --out
    assert a.run_id != b.run_id
    (tmp_path / "best.pt").write_text("a's")
    a.log_artifact(tmp_path / "best.pt", "checkpoints")
    (tmp_path / "best.pt").write_text("b's")
    b.log_artifact(tmp_path / "best.pt", "checkpoints")
    local = a.client.download_artifacts(a.run_id, "checkpoints/best.pt", str(tmp_path / "dl"))
    assert Path(local).read_text() == "a's"  # b never replaced a's artifact
    assert a.client.get_run(a.run_id).data.params["train.lr"] == "1"
    assert a.client.get_run(a.run_id).data.tags[OUT_TAG] == str(tmp_path / "runs" / "tiny")
    again = start_job_run("tiny", {}, out=tmp_path / "runs" / "tiny")
    assert again.run_id == a.run_id  # the same job again: resumed
    assert find_job_run("tiny", out=tmp_path / "alt" / "tiny").run_id == b.run_id
    assert start_job_run("other", {}, out=tmp_path / "runs" / "tiny").run_id not in (a.run_id, b.run_id)
    assert find_job_run("tiny") is None  # a lookup by name alone never finds an output's run


def test_a_run_left_running_by_a_killed_driver_is_ended_by_the_next_job(store, tmp_path):
    from aniformer.cli.locks import lock_output, release_locks
    from pipeline.tracking import start_job_run

    out = tmp_path / "run"
    killed = start_job_run("tiny", {}, out=out)  # its driver "dies": never ended
    other_name = start_job_run("tiny-b", {}, out=out)
    child = start_job_run("tiny-v", {}, out=out / "runs" / "v", parent_run_id=killed.run_id)
    elsewhere = start_job_run("tiny", {}, out=tmp_path / "busy")  # another output's live job
    assert start_job_run("tiny", {}, out=out).run_id == killed.run_id  # no lock held: nothing is ended
    client = killed.client
    assert client.get_run(other_name.run_id).info.status == "RUNNING"
    try:
        lock_output(out)
        resumed = start_job_run("tiny", {}, out=out)
    finally:
        release_locks()
    assert resumed.run_id == killed.run_id
    run = client.get_run(killed.run_id)
    assert run.info.status == "RUNNING" and "driver had died" in run.data.tags["aniformer.ended_by"]
    for ended in (other_name, child):
        assert client.get_run(ended.run_id).info.status == "KILLED"
    assert client.get_run(elsewhere.run_id).info.status == "RUNNING"


def test_name_only_lookups_keep_working_for_runs_of_no_output(store):
    """Sweep trials (tune.py) are opened by name and parent; found by name alone too."""
    from pipeline.tracking import find_job_run, start_job_run

    parent = start_job_run("sw", {}, out="/somewhere/sw")
    trial = start_job_run("sw-a0001", {}, parent_run_id=parent.run_id)
    assert start_job_run("sw-a0001", {}, parent_run_id=parent.run_id).run_id == trial.run_id
    assert find_job_run("sw-a0001").run_id == trial.run_id
    assert find_job_run("sw-a0001", parent_run_id=parent.run_id).run_id == trial.run_id
    assert find_job_run("sw-a0001", parent_run_id="f" * 32) is None


CREATE_RUN = textwrap.dedent("""
    import sys, time
    from pathlib import Path
    sys.path.insert(0, {root!r})
    from pipeline.tracking import quiet_mlflow, start_job_run
    quiet_mlflow()
    Path(sys.argv[2] + ".ready").touch()  # imports done: wait for the others
    while not Path({go!r}).exists():
        time.sleep(0.002)
    tracker = start_job_run(sys.argv[1], {{"a": 1}}, out=sys.argv[2])
    tracker.log_metrics({{"x": 1.0}}, step=1)
    tracker.end("FINISHED")
""")


def test_jobs_starting_together_on_a_fresh_store_all_succeed(tmp_path):
    """Four processes open a new mlflow.db at the same instant: one creates the tables, the others wait
    (without the lock this fails: "Online migration expected to match one row", "duplicate column")."""
    db, sync = tmp_path / "mlflow.db", tmp_path / "sync"
    sync.mkdir()
    env = {**os.environ, "MLFLOW_TRACKING_URI": f"sqlite:///{db}"}
    script = CREATE_RUN.format(root=str(ROOT), go=str(sync / "go"))
    procs = [subprocess.Popen([PY, "-c", script, f"job{i}", str(sync / f"out{i}")], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) for i in range(4)]
    deadline = time.time() + 300
    while len(list(sync.glob("*.ready"))) < 4 and time.time() < deadline and all(p.poll() is None for p in procs):
        time.sleep(0.05)
    (sync / "go").touch()
    outputs = [p.communicate(timeout=300)[0] for p in procs]
    assert [p.returncode for p in procs] == [0] * 4, "\n".join(o[-1500:] for o in outputs)
    from mlflow.tracking import MlflowClient

    client = MlflowClient(f"sqlite:///{db}")
    runs = client.search_runs([client.get_experiment_by_name("aniformer").experiment_id])
    assert sorted(r.data.tags["aniformer.job"] for r in runs) == [f"job{i}" for i in range(4)]
    assert all(r.info.status == "FINISHED" for r in runs)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mlflow.db", "sync"]  # no lock file left


def test_a_run_id_lookup_without_a_store_creates_none(tmp_path, monkeypatch):
    from pipeline.registry import resolve_checkpoint

    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    message = refusal(lambda: resolve_checkpoint("0123456789abcdef0123456789abcdef", tmp_path / "scratch"))
    assert "no tracking store" in message and not (tmp_path / "mlflow.db").exists()


# ------------------------------------------------------------------------------------ SIGTERM

SLEEPER = textwrap.dedent("""
    import sys, time
    from aniformer.cli.exits import run
    def main(argv):
        print("ready", flush=True)
        try:
            time.sleep(60)
        except SystemExit as e:  # what a library might do with it
            raise RuntimeError("wrapped") from e
    run(main)
""")


def test_sigterm_exits_143_with_one_line_whatever_the_stack_makes_of_it(read_line):
    proc = subprocess.Popen([PY, "-c", SLEEPER.format(root=str(ROOT))], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    assert read_line(proc.stdout, 60, "the sleeping job").strip() == "ready"
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode == 143 and err == "terminated (SIGTERM)\n", err
