"""Distributed training on the session's real multi-node Ray cluster, through `jobs/train.py`.

Every test runs the job as a subprocess with RAY_ADDRESS set to the session cluster, the way
`ray job submit` runs it, and an MLflow sqlite store of its own.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from mlflow.tracking import MlflowClient

from aniformer.checkpoint import KEYS, load_checkpoint, model_from_checkpoint

pytestmark = [pytest.mark.slow, pytest.mark.ray]

TWO_WORKERS = ["train.workers=2", "train.cpus_per_worker=0.5"]


@pytest.fixture(scope="module")
def tiny_bank(tmp_path_factory, ray_cluster, repo_root):
    from aniformer.cli.args import load_config
    from pipeline.data import data_config, generate_bank

    bank = tmp_path_factory.mktemp("train") / "bank"
    generate_bank(data_config(load_config(repo_root / "configs/tiny.yaml")), bank, progress=False)
    return bank


def start_job(repo_root, ray_address, out: Path, bank: Path, *overrides: str) -> subprocess.Popen:
    """The job as a subprocess; its output goes to a log file beside `out` (a pipe nobody reads while a
    test polls can fill up and block the job). `finish` and `output` read it."""
    env = {**os.environ, "RAY_ADDRESS": ray_address,
           "MLFLOW_TRACKING_URI": f"sqlite:///{out.parent / 'mlflow.db'}"}
    cmd = [sys.executable, str(repo_root / "jobs/train.py"), "--config", str(repo_root / "configs/tiny.yaml"),
           "--out", str(out), "--bank", str(bank), *overrides]
    log = out.parent / f"{out.name}.{time.monotonic_ns()}.log"
    with open(log, "w") as f:
        job = subprocess.Popen(cmd, env=env, stdout=f, stderr=subprocess.STDOUT, text=True, cwd=out.parent)
    job.log = log
    return job


def output(job: subprocess.Popen) -> str:
    return job.log.read_text(errors="replace")


def stop(job: subprocess.Popen) -> None:
    """Kill a job a failed test leaves running (it would hold the shared cluster's CPUs)."""
    if job.poll() is None:
        job.kill()
        job.wait()


def finish(job: subprocess.Popen, timeout: float = 900, code: int | None = 0) -> str:
    """Wait for the job; its exit status must be `code` (None: any failure)."""
    try:
        job.wait(timeout=timeout)
    finally:
        stop(job)
    assert job.returncode == code if code is not None else job.returncode != 0, output(job)[-3000:]
    return output(job)


def registered_epoch(out: Path) -> int:
    """The epoch of the checkpoint Ray Train has registered for the job at `out` (its checkpoint manager's
    snapshot, which is what a worker restart or a rerun restores from, `resume_epoch`); 0 while none is.
    A checkpoint file on disk is not enough: until it is registered a restore cannot find it."""
    from pipeline.checkpoints import resume_epoch
    from pipeline.trainer import ray_run_name

    return resume_epoch(out / "ray" / ray_run_name(out.name))


def wait_until(what: str, ready, job: subprocess.Popen, timeout: float = 600, every: float = 0.5):
    """Poll `ready()` until it is true while `job` runs; fail with `what` at the deadline or if the job ends."""
    deadline, problem = time.time() + timeout, None
    while True:
        assert job.poll() is None, f"the job ended before {what}:\n" + output(job)[-3000:]
        try:
            if value := ready():
                return value
        except Exception as e:  # a snapshot or the MLflow store caught mid-write: ask again
            problem = e
        assert time.time() < deadline, f"timed out waiting for {what} (last error: {problem!r})"
        time.sleep(every)


def wait_for_registered(out: Path, job: subprocess.Popen, epoch: int) -> int:
    """Until Ray Train has registered the job's checkpoint of `epoch` (or a later one); that epoch."""
    return wait_until(f"a registered checkpoint of epoch {epoch}",
                      lambda: (e := registered_epoch(out)) >= epoch and e, job)


def job_runs(out: Path):
    client = MlflowClient(f"sqlite:///{out.parent / 'mlflow.db'}")
    experiment = client.get_experiment_by_name("aniformer")
    if experiment is None:
        return client, []
    return client, client.search_runs([experiment.experiment_id], filter_string=f"tags.`aniformer.job` = '{out.name}'")


def logged(client, run, key) -> list[tuple[int, float]]:
    return [(m.step, m.value) for m in client.get_metric_history(run.info.run_id, key)]


def test_two_worker_ddp_on_two_nodes_is_tracked_in_mlflow(tmp_path, tiny_bank, ray_address, repo_root):
    """DDP over two nodes with the GPU execution options on, as a GPU cluster would run it, on CPU:
    torch.compile (inductor's C++ backend) around DDP (so DDPOptimizer splits the graph), activation
    checkpointing and an SDPA kernel preference. The checkpoints hold the plain model's weights."""
    out = tmp_path / "ddp"
    output = finish(start_job(repo_root, ray_address, out, tiny_bank, *TWO_WORKERS,
                              "train.placement_strategy=STRICT_SPREAD", "train.epochs=2", "train.render_every=1",
                              "train.compile=default", "train.activation_checkpointing=true",
                              "train.attention_kernels=[flash,math]"))
    assert str(out / "best.pt") in output and "MLflow run:" in output
    state = load_checkpoint(out / "best.pt")
    assert set(KEYS) <= set(state) and state["epoch"] >= 1
    assert not any("_orig_mod" in key or key.startswith("module.") for key in state["model"])
    model, _ = model_from_checkpoint(out / "last.pt")
    assert load_checkpoint(out / "last.pt")["epoch"] == 2

    client, runs = job_runs(out)
    assert len(runs) == 1
    run = runs[0]
    assert run.info.status == "FINISHED"
    assert run.data.tags["world_size"] == "2"
    params = run.data.params
    assert params["model.name"] == "aniformer" and "train.lr" in params
    assert params["train.compile"] == "default" and params["train.activation_checkpointing"] == "True"
    assert "flash" in params["train.attention_kernels"]
    for key in ("loss", "loss_rec", "loss_motion", "loss_appearance", "pmd_seen", "pmd_unseen",
                "samples_per_s", "peak_memory_gb"):
        history = logged(client, run, key)
        assert [step for step, _ in history] == [1, 2] and all(math.isfinite(v) for _, v in history), key
    unseen = logged(client, run, "pmd_unseen")
    assert state["epoch"] == min(unseen, key=lambda epoch_pmd: epoch_pmd[1])[0], "best.pt is not the lowest unseen PMD"
    artifacts = {a.path for a in client.list_artifacts(run.info.run_id, "filmstrips")}
    assert artifacts == {"filmstrips/epoch_0001.png", "filmstrips/epoch_0002.png"}
    assert [a.path for a in client.list_artifacts(run.info.run_id, "checkpoints")] == ["checkpoints/best.pt"]


def restore_nodes(cluster, count: int, node_args: dict) -> None:
    """Add worker nodes (`node_args`: as conftest makes them) until `cluster` has `count` again."""
    while len(cluster.list_all_nodes()) < count:
        cluster.add_node(**node_args)
    cluster.wait_for_nodes()


def test_killing_a_worker_node_restores_from_the_last_checkpoint(tmp_path, tiny_bank, ray_cluster, ray_address,
                                                                   repo_root, node_args):
    """A node lost mid-training: Ray Train restarts the workers from the last registered checkpoint and the
    run goes on from there. The kill lands once the checkpoint of epoch 1 is registered (so there is one to
    restore) and while epochs 2 and 3 are still to train; DDP ranks step in lockstep, so with a rank dead
    the run cannot finish without a restore."""
    epochs = 3
    out = tmp_path / "fault"
    nodes = len(ray_cluster.list_all_nodes())
    victim = next(node for node in ray_cluster.list_all_nodes() if node is not ray_cluster.head_node)
    # STRICT_SPREAD: one training worker is on each node, so one of them dies with `victim`.
    job = start_job(repo_root, ray_address, out, tiny_bank, *TWO_WORKERS, "train.placement_strategy=STRICT_SPREAD",
                    f"train.epochs={epochs}", "train.max_failures=3")
    try:
        registered = wait_for_registered(out, job, 1)
        assert registered < epochs, f"the checkpoint of epoch {registered} was registered before the kill"
        ray_cluster.remove_node(victim, allow_graceful=False)  # SIGKILL, like a lost machine
        assert job.poll() is None, "the job ended before the node was killed:\n" + output(job)[-3000:]
        restore_nodes(ray_cluster, nodes, node_args)  # STRICT_SPREAD needs two nodes to restart the workers
        console = finish(job)
    finally:  # never leave the job running nor the shared cluster short of a node, whatever failed
        stop(job)
        restore_nodes(ray_cluster, nodes, node_args)

    client, (run,) = job_runs(out)
    resumed = logged(client, run, "resumed_from_epoch")  # logged only by workers that started from a checkpoint
    assert len(resumed) == 1, f"expected one restore, got {resumed}"
    (step, restored), = resumed
    # from a checkpoint registered at or after the kill point, with epochs still to train
    assert step == restored and registered <= restored < epochs, resumed
    epochs_logged = [value for _, value in logged(client, run, "epoch")]
    # The epoch in flight at the kill may be redone; none up to the restored checkpoint is.
    assert all(epochs_logged.count(e) == 1 for e in range(1, int(restored) + 1)), \
        f"the epoch counter restarted: {epochs_logged}"
    assert sorted(set(epochs_logged)) == [1.0, 2.0, 3.0], epochs_logged
    assert epochs_logged[-1] == epochs and load_checkpoint(out / "last.pt")["epoch"] == epochs
    assert run.info.status == "FINISHED"
    # the console says it in a line each, not in Ray's controller traceback
    assert f"resumed from the checkpoint of epoch {int(restored)} after a worker group restart" in console, console[-3000:]
    assert "Graceful shutdown of backend failed" not in console, console[-3000:]


def test_an_interrupted_job_ends_its_run_killed_and_a_rerun_resumes_it(tmp_path, tiny_bank, ray_address, repo_root):
    """Ctrl-C (SIGINT: Ray Train's own handler aborts the fit, the job exits 1) and `ray job stop` or kill
    (SIGTERM: `run`'s handler, exit 143 with one line) both end the MLflow run KILLED, never RUNNING, and
    release the --out lock; each interrupted run is resumed by the next run of the same command, which
    continues the same MLflow run from the checkpoint Ray Train had registered."""
    out = tmp_path / "resume"
    job = start_job(repo_root, ray_address, out, tiny_bank, "train.epochs=3")
    # Not just a checkpoint file on disk: Ray Train must have registered it, or a rerun has nothing to restore.
    wait_for_registered(out, job, 1)
    job.send_signal(signal.SIGINT)
    finish(job, timeout=120, code=None)  # Ray Train's own SIGINT handler aborts the run and exits 1
    client, (run,) = job_runs(out)
    assert run.info.status == "KILLED" and not (out / ".lock").exists()
    after_sigint = registered_epoch(out)

    job = start_job(repo_root, ray_address, out, tiny_bank, "train.epochs=3")
    # the rerun restored (it logs resumed_from_epoch as its workers start), and trains on: now stop it
    wait_until("the rerun's restore", lambda: resumed_epochs(out), job)
    job.send_signal(signal.SIGTERM)
    assert finish(job, timeout=120, code=143).splitlines()[-1] == "terminated (SIGTERM)"
    client, (run,) = job_runs(out)
    assert run.info.status == "KILLED" and not (out / ".lock").exists()
    after_sigterm = registered_epoch(out)

    finish(start_job(repo_root, ray_address, out, tiny_bank, "train.epochs=3"))
    client, runs = job_runs(out)
    assert len(runs) == 1 and runs[0].info.status == "FINISHED"  # the same MLflow run, continued
    # each rerun restored exactly the checkpoint registered when the run before it was interrupted
    assert sorted(resumed_epochs(out)) == sorted([after_sigint, after_sigterm]), (after_sigint, after_sigterm)
    assert 1 <= after_sigint <= after_sigterm < 3
    assert load_checkpoint(out / "last.pt")["epoch"] == 3
    # the same command once more: nothing left to train, and no worker group restarted to say so
    console = finish(start_job(repo_root, ray_address, out, tiny_bank, "train.epochs=3"))
    assert "resumed from the checkpoint of epoch 3\n" in console and "worker group restart" not in console, console[-3000:]


def test_a_killed_training_controller_is_one_line_that_says_how_to_resume(tmp_path, tiny_bank, ray_address, repo_root):
    """kill -9 of Ray Train's controller actor mid-run (a fault of bench/soak.py): the job exits 2 with one
    line that says the same command resumes, not Ray's 40-line ActorDiedError traceback."""
    from ray.util.state import list_actors

    def controllers() -> dict:
        return {a.actor_id: a for a in list_actors(filters=[("class_name", "=", "TrainController"), ("state", "=", "ALIVE")])}

    out = tmp_path / "controller"
    others = controllers()  # the shared cluster's: earlier tests' jobs may still be ending
    job = start_job(repo_root, ray_address, out, tiny_bank, "train.epochs=20")
    try:
        wait_for_registered(out, job, 1)
        (controller,) = [a for actor_id, a in controllers().items() if actor_id not in others]
        os.kill(controller.pid, signal.SIGKILL)
        console = finish(job, timeout=300, code=2)
    finally:
        stop(job)
    assert "Traceback" not in console, console[-3000:]
    # Ray's own lines (its placement group cleaner) may still arrive after ours
    (error,) = [line for line in console.splitlines() if line.startswith("error:")]
    assert error.startswith("error: training interrupted: Ray Train's controller died"), console[-3000:]
    assert "the same command resumes from the last checkpoint" in error


def resumed_epochs(out: Path) -> list[float]:
    """The `resumed_from_epoch` values the job's MLflow run has logged (one per restore)."""
    client, runs = job_runs(out)
    return [value for _, value in logged(client, runs[0], "resumed_from_epoch")] if runs else []


BAD_OVERRIDES = [("train.epochs=0", "epochs must be >= 1"),
                 ("model.attention=both", "attention must be one of"),
                 ("model.name=limp", "unknown name"),
                 ("train.wings=3", "unknown key(s) in [train]"),
                 ("train.compile=fast", "compile must be one of"),
                 ("train.attention_kernels=[flash,turbo]", "attention_kernels: unknown ['turbo']")]


@pytest.mark.parametrize(("override", "message"), BAD_OVERRIDES, ids=[o for o, _ in BAD_OVERRIDES])
def test_bad_config_fails_with_one_line_before_starting_ray(tmp_path, repo_root, capsys, job_main, override, message):
    from aniformer.cli.exits import run

    with pytest.raises(SystemExit) as exit_:
        run(job_main("train"), ["--config", str(repo_root / "configs/tiny.yaml"), "--out", str(tmp_path / "x"), override])
    stderr = capsys.readouterr().err
    assert exit_.value.code == 2 and stderr.strip().count("\n") == 0 and message in stderr, stderr
    assert not (tmp_path / "x").exists()


def test_bad_config_exits_2_from_the_shell(tmp_path, repo_root):
    run = subprocess.run([sys.executable, str(repo_root / "jobs/train.py"), "--config",
                          str(repo_root / "configs/tiny.yaml"), "--out", str(tmp_path / "x"), "train.epochs=0"],
                         capture_output=True, text=True, timeout=120, env={**os.environ, "RAY_ADDRESS": ""})
    assert run.returncode == 2 and run.stderr.strip() == "error: [train] epochs must be >= 1, got 0", run.stderr
    assert not (tmp_path / "x").exists()


def pair_order_recorder(record: Path):
    """A training loop that records the (epoch, index) ids of its train batches to ``record``;
    made by a function so that cloudpickle ships it by value (workers cannot import tests)."""
    def record_pair_order(config):
        import json

        import ray.train

        ids = []
        for batch in ray.train.get_dataset_shard("train").iter_torch_batches(batch_size=256):
            ids += (batch["epoch"] * 100_000 + batch["index"]).tolist()
        record.write_text(json.dumps(ids))

    return record_pair_order


def recorded_pair_ids(spec, bank, storage: Path, name: str) -> list[int]:
    import json

    import numpy as np

    from pipeline.trainer import build_trainer

    record = storage.parent / f"{name}.ids.json"
    trainer = build_trainer(spec, bank, storage, name, None, np.zeros((1, 3), np.int64),
                            loop=pair_order_recorder(record))
    assert trainer.fit().error is None
    return json.loads(record.read_text())


def test_training_reads_pairs_in_id_order(tmp_path, tiny_bank, repo_root):
    """build_trainer's ingest preserves block order: the same config and seed give the same batches
    (and so the same model), however Ray Data's tasks happen to finish."""
    from aniformer.cli.args import load_config
    from pipeline.run_spec import RunSpec

    # 2 epochs x 3,000 pairs: several blocks and assembly tasks, which finish in any order
    spec = RunSpec.from_config(load_config(repo_root / "configs/tiny.yaml", ["train.epochs=2", "data.pairs_per_epoch=3000"]))
    ids = recorded_pair_ids(spec, tiny_bank, tmp_path / "ray", "order")
    assert ids == [e * 100_000 + i for e in (0, 1) for i in range(3000)]


def test_a_worker_error_is_one_line_with_its_root_cause_and_the_logs(tmp_path, tiny_bank, ray_address, repo_root):
    """On CPU no cuDNN attention exists: the worker's forward raises. Ray Train's fit() raises a
    WorkerGroupError around it; the job prints the root cause in one line and exits 2."""
    out = tmp_path / "fails"
    log = finish(start_job(repo_root, ray_address, out, tiny_bank, "train.attention_kernels=[cudnn]",
                           "train.max_failures=0"), code=2)
    last = log.strip().splitlines()[-1]
    assert last.startswith("error: training failed on worker rank 0: RuntimeError: No viable backend for "
                           "scaled_dot_product_attention"), log[-3000:]
    assert "(logs: /" in last and "Traceback" not in last
    client, (run,) = job_runs(out)
    assert run.info.status == "FAILED"




def test_a_unicode_named_run_resumes_past_a_truncated_checkpoint_reading_only_untrained_epochs(
        tmp_path, tiny_bank, ray_address, repo_root):
    """One scenario, three guarantees.
    A non-ASCII --out, and so job name: MLflow keeps the name, Ray Train is given an ASCII one (it encodes
    its metric tags as ASCII; the run used to fail with a UnicodeEncodeError), and a rerun finds that same
    Ray directory and resumes from it.
    A truncated latest Ray checkpoint (a crash or a full disk while it was written): the rerun resumes
    from the one before it instead of failing every retry.
    The resumed run's train dataset starts at the restored epoch (no pairs of earlier epochs are made and
    skipped), and the real loop trains on from there."""
    from aniformer.cli.args import load_config
    from pipeline.checkpoints import resume_epoch
    from pipeline.run_spec import RunSpec
    from pipeline.trainer import ray_run_name

    out = tmp_path / "ünï cødé"
    ray_name = ray_run_name(out.name)
    assert resume_epoch(out / "ray" / ray_name) == 0  # no run yet
    assert "UnicodeEncodeError" not in finish(start_job(repo_root, ray_address, out, tiny_bank, "train.epochs=2"))
    assert ray_name.isascii() and sorted(p.name for p in (out / "ray").iterdir() if p.is_dir()) == [ray_name]
    client, (run,) = job_runs(out)  # found by the real name
    unseen = logged(client, run, "pmd_unseen")
    assert load_checkpoint(out / "best.pt")["epoch"] == min(unseen, key=lambda epoch_pmd: epoch_pmd[1])[0]
    assert load_checkpoint(out / "last.pt")["epoch"] == 2

    first, latest = sorted(p for p in (out / "ray" / ray_name).glob("checkpoint_*") if p.is_dir())
    assert load_checkpoint(first)["epoch"] == 1 and load_checkpoint(latest)["epoch"] == 2
    payload = (latest / "checkpoint.pt").read_bytes()
    (latest / "checkpoint.pt").write_bytes(payload[: len(payload) // 2])
    assert resume_epoch(out / "ray" / ray_name) == 1  # past the truncated one

    # what the rerun's train dataset holds: the pairs of epochs 2 and 3 only (ids epoch * 100,000 + index)
    three = RunSpec.from_config(load_config(repo_root / "configs/tiny.yaml", ["train.epochs=3"]))
    ids = recorded_pair_ids(three, tiny_bank, out / "ray", out.name)
    assert ids == [e * 100_000 + i for e in (1, 2) for i in range(three.data.pairs_per_epoch)]

    log = finish(start_job(repo_root, ray_address, out, tiny_bank, "train.epochs=3"))
    assert f"resuming from the newest intact checkpoint, {first.name} (epoch 1)" in log, log[-3000:]
    assert sorted(p.name for p in (out / "ray").iterdir() if p.is_dir()) == [ray_name]  # the same Ray directory
    client, (run,) = job_runs(out)  # the same MLflow run, continued, found by the real name
    assert [v for _, v in logged(client, run, "resumed_from_epoch")] == [1.0]
    assert sorted(v for _, v in logged(client, run, "epoch")) == [1.0, 2.0, 2.0, 3.0]
    assert load_checkpoint(out / "last.pt")["epoch"] == 3 and run.info.status == "FINISHED"
