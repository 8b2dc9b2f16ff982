"""Sweeps (pipeline/tune.py, jobs/sweep.py): the memory gate, MLflow parent/child runs, restore.

The end-to-end test runs `jobs/sweep.py` as a subprocess on the session's Ray cluster (RAY_ADDRESS),
interrupts it (SIGINT) once a trial has finished, and runs the same command again: the restored
sweep must finish only the trials that had not finished.
"""

from __future__ import annotations

import csv
import math
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from aniformer.cli.args import load_config
from aniformer.errors import UserError

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs/sweep_tiny.yaml"


# ---------------------------------------------------------------- fast: config, space, gate, status


def test_sweep_config_parses_and_rejects_bad_sections():
    from pipeline.run_spec import RunSpec
    from pipeline.sweep_config import apply_params, split_config

    base, sweep = split_config(load_config(CONFIG))
    RunSpec.from_config(base)
    assert sweep.window[0] < sweep.window[1] and sweep.rec[0] < sweep.rec[1]
    trial = apply_params(base, {"rec": 2.0, "motion": 1e-3, "appearance": 2e-3, "window": 6, "batch_size": 8})
    spec = RunSpec.from_config(trial)
    assert (spec.loss.rec, spec.loss.motion, spec.loss.appearance) == (2.0, 1e-3, 2e-3)
    assert spec.data.window == spec.model.window == 6 and spec.train.batch_size == 8
    assert base["data"]["window"] == 3  # the base config is not modified
    for override, message in [("sweep.rec=[0, 1]", "0 < low <= high"), ("sweep.search=grid", "search must be"),
                              ("sweep.wings=1", "unknown key(s) in [sweep]"),
                              ("sweep.points=[{depth: 3}]", "unknown parameter")]:
        with pytest.raises(UserError, match=re.escape(message)):
            split_config(load_config(CONFIG, [override]))


def test_points_are_completed_for_the_search():
    from pipeline.sweep_config import complete_points, split_config

    _, sweep = split_config(load_config(CONFIG, ["sweep.batch_size=[4, 64]", "sweep.points=[{window: 8, batch_size: 64}]"]))
    (point,) = complete_points(sweep, base_batch=4)
    assert point["window"] == 8 and point["batch_size"] == 64
    assert point["rec"] == pytest.approx(math.sqrt(sweep.rec[0] * sweep.rec[1]))
    _, sweep = split_config(load_config(CONFIG, ["sweep.points=[{batch_size: 64}]"]))
    with pytest.raises(UserError, match="not searched"):
        complete_points(sweep, base_batch=4)


def test_gate_adjusts_then_skips_oversized_trials():
    from pipeline.memory_gate import gate
    from pipeline.run_spec import RunSpec
    from pipeline.sweep_config import apply_params, split_config

    base, sweep = split_config(load_config(CONFIG, ["sweep.memory_limit_gb=1.2"]))
    def plan(**params):
        return gate(RunSpec.from_config(apply_params(base, params)), vertices=369, faces=734, sweep=sweep)

    assert plan(window=3, batch_size=4).status == "ok"
    adjusted = plan(window=8, batch_size=64)
    assert adjusted.status == "adjusted_memory" and adjusted.predicted_gb <= 1.2 < adjusted.requested_gb
    assert adjusted.batch_size * adjusted.grad_accumulation == 64
    assert plan(window=8, batch_size=4096).status == "skipped_memory"  # would need > 16x accumulation


def test_trial_status():
    from pipeline.tune import trial_status

    assert trial_status({"memory_decision": "ok", "epoch": 2}, None, 2) == "ok"
    assert trial_status({"memory_decision": "adjusted_memory", "epoch": 2}, None, 2) == "adjusted_memory"
    assert trial_status({"memory_decision": "ok", "epoch": 1}, None, 2) == "early_stopped"
    assert trial_status({"memory_decision": "skipped_memory", "epoch": 0}, None, 2) == "skipped_memory"
    assert trial_status({"memory_decision": "ok", "epoch": 1}, RuntimeError("x"), 2) == "failed"
    assert trial_status({}, None, 2) == "failed"


def test_interrupted_trials_runs_are_ended_even_before_their_first_report(tmp_path, monkeypatch):
    """A trial interrupted before its first epoch report has an MLflow run but no run id in any
    Tune result: its run is found by job name and ended, never left RUNNING."""
    from pipeline.tracking import start_job_run
    from pipeline.tune import end_interrupted_runs

    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    parent = start_job_run("sw", {})
    started = start_job_run("sw-a0001", {}, parent_run_id=parent.run_id)  # no epoch reported yet
    finished = start_job_run("sw-a0002", {}, parent_run_id=parent.run_id)
    finished.end("FINISHED")
    end_interrupted_runs("sw", ["a0001", "(not created)"], "aniformer")
    run = started.client.get_run(started.run_id)
    assert run.info.status == "KILLED" and run.data.tags["status"] == "interrupted"
    assert finished.client.get_run(finished.run_id).info.status == "FINISHED"
    assert start_job_run("sw-a0001", {}).run_id == started.run_id  # the restored trial reopens it


def test_a_trial_failing_before_its_first_report_ends_its_run_failed(tmp_path, monkeypatch, capsys):
    """The driver callback finds a trial's run by job name, not from its (absent) results, and says why the
    trial failed in one line (Tune's own traceback of it is dropped)."""
    import logging
    from types import SimpleNamespace

    from pipeline.tracking import start_job_run
    from pipeline.tune import SweepRuns

    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    run = start_job_run("sw-a0001", {})
    callback = SweepRuns(epochs=2, sweep_name="sw", trials_dir=str(tmp_path / "trials"), experiment="aniformer")
    error_file = tmp_path / "error.txt"
    error_file.write_text("Traceback (most recent call last):\n  File \"x.py\", line 1, in <module>\n"
                          "ray.exceptions.ActorDiedError: The actor died unexpectedly before finishing this task.\n")
    callback.on_trial_error(0, [], SimpleNamespace(trial_id="a0001", last_result=None, error_file=str(error_file)))
    ended = run.client.get_run(run.run_id)
    assert ended.info.status == "FAILED" and ended.data.tags["status"] == "failed"
    assert capsys.readouterr().out == ("sweep: trial a0001 failed: ray.exceptions.ActorDiedError: The actor died "
                                       f"unexpectedly before finishing this task. (traceback: {error_file})\n")
    tune_controller = logging.getLogger("ray.tune.execution.tune_controller")
    assert not tune_controller.filter(logging.makeLogRecord({"msg": "Trial task failed for trial run_trial_34d92aa3"}))
    assert tune_controller.filter(logging.makeLogRecord({"msg": "Trying to restore the experiment"}))
    callback.on_trial_error(0, [], SimpleNamespace(trial_id="a0002", last_result=None, error_file="error.txt"))  # no run


def _trial(i: int, status: str, config: dict, result: dict | None = None, best: float | None = None):
    """What the sweep's reporter and callbacks read of a Tune trial."""
    from types import SimpleNamespace

    return SimpleNamespace(trial_id=f"t{i:04d}", status=status, config=config, last_result=result or {},
                           metric_analysis={"pmd_unseen": {"min": best}} if best is not None else {})


def _reporter(*overrides: str, every: float = 0.0):
    from pipeline.sweep_config import split_config
    from pipeline.sweep_table import SweepReporter

    base, sweep = split_config(load_config(CONFIG, list(overrides)))
    reporter = SweepReporter(base, sweep, sweep_name="sw", epochs=2, vertices=369, faces=734, every=every)
    reporter.setup(start_time=time.time() - 75, total_samples=5, metric="pmd_unseen", mode="min")
    return reporter


RAN = {"memory_decision": "ok", "requested_batch_size": 4, "run_batch_size": 4, "grad_accumulation": 1,
       "predicted_memory_gb": 0.862, "peak_memory_gb": 0.735}


def test_live_table_shows_weights_window_memory_status_epoch_and_best_pmd(capsys, monkeypatch):
    """The console's trial table (SweepReporter): a row per trial with its lambdas, T, batch, predicted
    memory (before the trial reported: the gate's prediction), the sweep's status, epochs, best PMD."""
    from types import SimpleNamespace

    from pipeline import sweep_table

    # the table's clock stands still ~75 s after the sweep's start: planning the trials took 44 s on a loaded machine
    frozen = time.time()
    monkeypatch.setattr(sweep_table, "time", SimpleNamespace(time=lambda: frozen))
    reporter = _reporter("sweep.memory_limit_gb=1.2")
    trials = [
        _trial(0, "TERMINATED", {"rec": 8.46, "motion": 1.41e-4, "appearance": 2.37e-3, "window": 5},
               {**RAN, "epoch": 2, "pmd_unseen": 560.0}, best=550.06),
        _trial(1, "TERMINATED", {"rec": 0.7, "motion": 8.7e-4, "appearance": 2.1e-4, "window": 8},
               {**RAN, "epoch": 1, "pmd_unseen": 1216.4}, best=1216.4),
        _trial(2, "RUNNING", {"rec": 1.0, "motion": 1e-3, "appearance": 1e-3, "window": 8, "batch_size": 64}),
        _trial(3, "PENDING", {"rec": 2.0, "motion": 1e-4, "appearance": 1e-4, "window": 8, "batch_size": 4096}),
        _trial(4, "ERROR", {"rec": 3.0, "motion": 1e-4, "appearance": 1e-4, "window": 3}, {**RAN, "epoch": 1}),
    ]
    assert reporter.should_report(trials)
    reporter.report(trials, False)
    live = capsys.readouterr().out
    lines = live.splitlines()
    assert re.fullmatch(r"== sweep sw: 3/5 trials finished \(1 early_stopped, 1 failed, 1 ok\), 1 running, 1 pending; "
                        r"1 min 1\d s ==", lines[0]), lines[0]
    assert lines[1] == "best so far: trial t0000, PMD unseen 550.1 (x1e-4)"
    header = next(line for line in lines if line.startswith("| trial"))
    assert [c.strip() for c in header.strip("|").split("|")] == [
        "trial", "status", "rec", "motion", "appearance", "T", "batch", "pred GB", "peak GB", "epoch", "best PMD"]
    rows = {line.split("|")[1].strip(): [c.strip() for c in line.strip("|").split("|")]
            for line in lines if line.startswith("| t0")}
    assert rows["t0000"] == ["t0000", "ok", "8.46", "0.000141", "0.00237", "5", "4", "0.86", "0.73", "2/2", "550.1"]
    assert rows["t0001"][1] == "early_stopped" and rows["t0001"][9:] == ["1/2", "1216"]
    # not reported yet: the gate's decision, as run_trial will apply it (64 -> 16 x 4 fits 1.2 GB)
    assert rows["t0002"][1] == "running" and rows["t0002"][6] == "64->16x4" and 0 < float(rows["t0002"][7]) <= 1.2
    assert rows["t0003"][1] == "pending" and rows["t0003"][6] == "4096 (skip)" and float(rows["t0003"][7]) > 1.2
    assert rows["t0004"][1] == "failed" and rows["t0004"][10] == ""
    assert not reporter.should_report(trials)  # nothing changed: nothing printed (a log stays short)
    trials[2].last_result = {**RAN, "epoch": 1, "pmd_unseen": 700.0}
    trials[2].metric_analysis = {"pmd_unseen": {"min": 700.0}}
    assert reporter.should_report(trials)
    reporter.report(trials, True)
    final = capsys.readouterr().out
    assert final.startswith("== sweep sw: 5 trials (1 early_stopped, 1 failed, 1 ok, 1 pending, 1 running) in 1 min 1")
    assert "| t0002 | running" in final and "700" in final


def test_live_table_is_throttled():
    reporter = _reporter(every=60)
    trials = [_trial(0, "PENDING", {"rec": 1.0, "motion": 1e-3, "appearance": 1e-3, "window": 3})]
    assert reporter.should_report(trials)
    reporter.report(trials, False)
    trials[0].status = "RUNNING"
    assert not reporter.should_report(trials)  # changed, but printed less than `every` seconds ago
    assert reporter.should_report(trials, done=True)  # the final table always


def test_ended_trials_runs_get_their_best_pmd_and_predicted_memory_as_metrics(tmp_path, monkeypatch):
    """The compare view plots metrics: each child run gets best_pmd_unseen (the minimum over its epochs,
    not the last epoch's) and predicted_memory_gb when its trial ends."""
    from pipeline.sweep_table import compare_link
    from pipeline.tracking import start_job_run
    from pipeline.tune import SweepRuns

    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    parent = start_job_run("sw", {})
    run = start_job_run("sw-t0000", {}, parent_run_id=parent.run_id)
    callback = SweepRuns(epochs=2, sweep_name="sw", trials_dir=str(tmp_path / "trials"), experiment="aniformer")
    callback.on_trial_complete(0, [], _trial(0, "TERMINATED", {}, {**RAN, "epoch": 2, "pmd_unseen": 560.0}, best=550.5))
    ended = run.client.get_run(run.run_id)
    assert ended.info.status == "FINISHED" and ended.data.tags["status"] == "ok"
    assert ended.data.metrics == {"best_pmd_unseen": 550.5, "predicted_memory_gb": 0.862}
    assert [m.step for m in run.client.get_metric_history(run.run_id, "best_pmd_unseen")] == [2]
    rows = [{"mlflow_run_id": run.run_id, "status": "ok"}, {"mlflow_run_id": "f" * 32, "status": "skipped_memory"},
            {"mlflow_run_id": "", "status": "failed"}]
    link = compare_link(parent, rows)
    experiment = parent.client.get_run(parent.run_id).info.experiment_id
    assert link == (f"http://127.0.0.1:5000/#/compare-runs?runs=%5B%22{run.run_id}%22%5D"
                    f"&experiments=%5B%22{experiment}%22%5D")
    assert compare_link(parent, rows[1:]) is None


# ---------------------------------------------------------------- end to end on the Ray cluster

SWEEP = ["sweep.num_samples=3", "sweep.max_concurrent=1", "sweep.search=optuna", "sweep.seed=1",
         "sweep.memory_limit_gb=1.2", "sweep.batch_size=[4, 64, 4096]",
         # in this order: 4096 cannot fit within 16x accumulation (skipped); 64 fits at 16 x 4 (adjusted);
         # batch 4 fits (ok) and is the trial the interruption catches running
         "sweep.points=[{window: 8, batch_size: 4096}, {window: 8, batch_size: 64}, {window: 3, batch_size: 4}]",
         "train.epochs=1", "train.render_every=1"]


def _sweep_job(out: Path, bank: Path, ray_address: str, log: Path) -> subprocess.Popen:
    """The sweep as a subprocess; its output goes to `log` (Tune and Ray Data print a lot: a pipe
    nobody reads while the test polls would fill up and block the sweep's driver)."""
    env = {**os.environ, "RAY_ADDRESS": ray_address, "MLFLOW_TRACKING_URI": f"sqlite:///{out.parent / 'mlflow.db'}"}
    cmd = [sys.executable, str(ROOT / "jobs/sweep.py"), "--config", str(CONFIG), "--out", str(out),
           "--bank", str(bank), *SWEEP]
    with open(log, "w") as f:
        return subprocess.Popen(cmd, env=env, stdout=f, stderr=subprocess.STDOUT, text=True, cwd=out.parent,
                                start_new_session=True)


def _tail(log: Path, n: int = 4000) -> str:
    return log.read_text(errors="replace")[-n:]


def _runs(out: Path):
    from mlflow.tracking import MlflowClient

    client = MlflowClient(f"sqlite:///{out.parent / 'mlflow.db'}")
    experiment = client.get_experiment_by_name("aniformer")
    runs = client.search_runs([experiment.experiment_id]) if experiment else []
    parent = [r for r in runs if r.data.tags.get("aniformer.job") == out.name]
    children = [r for r in runs if r.data.tags.get("mlflow.parentRunId") in {p.info.run_id for p in parent}]
    return client, parent, children


@pytest.fixture(scope="module")
def sweep_run(tmp_path_factory, ray_address):
    """Run the sweep, interrupt it once two trials have ended and the third is running, run it again;
    what each saw (`before`: the trials' MLflow runs as the interrupted sweep left them)."""
    from pipeline.data import data_config, generate_bank

    root = tmp_path_factory.mktemp("sweep")
    bank = root / "bank"
    generate_bank(data_config(load_config(CONFIG)), bank, progress=False)
    out = root / "tiny_sweep"
    first_log, second_log = root / "first.log", root / "second.log"
    # The sweep needs the whole cluster: CPUs still held by an earlier test would starve its trials.
    _until_idle()
    job = _sweep_job(out, bank, ray_address, first_log)
    try:
        # The interruption is driven by what the sweep has done, not by time: the two trials before the
        # last have ended (the driver callback gave their runs a final status) and the last one has
        # started its trainer (its placement group recorded; its epoch is still to come), so the restored
        # sweep has an unfinished trial to resume.
        # "starting sweep" is printed once the job has made its MLflow store and parent run: polling the
        # store earlier could race the job creating its tables.
        _until("the sweep's start", lambda: "starting sweep" in first_log.read_text(errors="replace"), job, first_log)
        _until("two trials ended and the third training", lambda: _third_is_training(out), job, first_log)
        job.send_signal(signal.SIGINT)  # Tune saves the experiment state and stops
        _exit_code(job, first_log, 240, "the interrupted sweep")
    finally:
        if job.poll() is None:
            os.killpg(job.pid, signal.SIGKILL)
    _, _, children = _runs(out)
    before = {c.data.tags["trial_id"]: c for c in children}
    second = _sweep_job(out, bank, ray_address, second_log)
    try:
        _exit_code(second, second_log, 900, "the restored sweep")
    finally:
        if second.poll() is None:
            os.killpg(second.pid, signal.SIGKILL)
    assert second.returncode == 0, _tail(second_log)
    return {"out": out, "bank": bank, "first": (job.returncode, first_log.read_text(errors="replace")),
            "second": second_log.read_text(errors="replace"), "before": before}


def _third_is_training(out: Path) -> bool:
    """Two trials' runs ended and the third's open, its trainer started (its placement group recorded)."""
    from pipeline.tune import PLACEMENT_GROUP_FILE

    _, _, children = _runs(out)
    running = [c.data.tags.get("trial_id") for c in children if c.info.status == "RUNNING"]
    return (len(children) - len(running), len(running)) == (2, 1) and \
        (out / "trials" / f"{out.name}-{running[0]}" / PLACEMENT_GROUP_FILE).is_file()


def _cluster_state() -> str:
    """The session cluster's free CPUs and live placement groups: what a sweep waiting for CPUs waits on."""
    import ray

    groups = {g: (v["state"], v["bundles"]) for g, v in ray.util.placement_group_table().items()
              if v["state"] != "REMOVED"}
    return (f"CPU free {ray.available_resources().get('CPU', 0)} of {ray.cluster_resources().get('CPU', 0)}, "
            f"live placement groups {groups}")


def _until_idle(timeout: float = 120) -> None:
    import ray

    deadline = time.time() + timeout
    while ray.available_resources().get("CPU", 0) < ray.cluster_resources().get("CPU", 0):
        assert time.time() < deadline, f"the cluster is still busy after {timeout:.0f} s: {_cluster_state()}"
        time.sleep(1)


def _exit_code(job: subprocess.Popen, log: Path, timeout: float, what: str) -> int:
    """The job's exit code; at the deadline a failure with what the cluster holds and the job's log."""
    try:
        return job.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        raise AssertionError(f"{what} did not end within {timeout:.0f} s; {_cluster_state()}\n{_tail(log)}") from None


def _until(what: str, ready, job: subprocess.Popen, log: Path, timeout: float = 600) -> None:
    """Poll `ready()` every second until true; fail at the deadline, or at once if the sweep ends first."""
    deadline, problem = time.time() + timeout, None
    while True:
        assert job.poll() is None, f"the sweep ended before {what}:\n{_tail(log)}"
        try:
            if ready():
                return
        except Exception as e:  # the store being created or migrated by the job: ask again
            problem = e
        assert time.time() < deadline, f"timed out waiting for {what} (last error: {problem!r})\n{_tail(log)}"
        time.sleep(1)


def _summary(out: Path) -> list[dict]:
    with open(out / "summary.csv") as f:
        return list(csv.DictReader(f))




@pytest.mark.slow
@pytest.mark.ray
def test_interrupted_sweep_restores_without_rerunning_finished_trials(sweep_run):
    code, output = sweep_run["first"]
    assert code != 0 and "run the same command again" in output, output[-3000:]  # and said so
    assert "restoring sweep" in sweep_run["second"]
    client, _, children = _runs(sweep_run["out"])
    after = {c.data.tags["trial_id"]: c for c in children}
    rows = _summary(sweep_run["out"])
    assert len(rows) == 3 and {r["trial_id"] for r in rows} == set(after)
    before = sweep_run["before"]
    assert set(before) == set(after), "the restored sweep made new trials"
    # The interruption came after two trials had ended and while the third ran (the fixture waits for
    # exactly that): the first two ended with their final status, the third was interrupted.
    assert {trial: (run.info.status, run.data.tags["status"]) for trial, run in before.items()} == {
        trial_of(before, 8, 4096): ("KILLED", "skipped_memory"),  # never trained: MLflow has no "skipped"
        trial_of(before, 8, 64): ("FINISHED", "adjusted_memory"),
        trial_of(before, 3, 4): ("KILLED", "interrupted")}
    for trial_id in (trial_of(before, 8, 4096), trial_of(before, 8, 64)):
        # finished before the interruption: not run again (same status and end, no resumed training)
        run = before[trial_id]
        assert (after[trial_id].info.status, after[trial_id].data.tags["status"]) == (
            run.info.status, run.data.tags["status"]), trial_id
        assert after[trial_id].info.end_time == run.info.end_time, trial_id
        assert not client.get_metric_history(run.info.run_id, "resumed_from_epoch")
        epochs = [m.step for m in client.get_metric_history(run.info.run_id, "epoch")]
        assert epochs == ([] if run.data.tags["status"] == "skipped_memory" else [1]), f"trial {trial_id}: {epochs}"
    interrupted = trial_of(before, 3, 4)  # restored and finished by the second run, in the same MLflow run
    assert after[interrupted].info.run_id == before[interrupted].info.run_id
    assert (after[interrupted].info.status, after[interrupted].data.tags["status"]) == ("FINISHED", "ok")
    assert [m.step for m in client.get_metric_history(after[interrupted].info.run_id, "epoch")] == [1]


def trial_of(runs: dict, window: int, batch_size: int) -> str:
    """The trial id of the sweep point (window, requested batch size) among `runs` ({trial id: MLflow run})."""
    (trial_id,) = [t for t, r in runs.items() if r.data.params["data.window"] == str(window)
                   and r.data.tags["requested_batch_size"] == str(batch_size)]
    return trial_id


@pytest.mark.slow
@pytest.mark.ray
def test_oversized_trials_are_gated_before_launch_and_summarised(sweep_run):
    from pipeline.data import data_config, prepare_bank
    from pipeline.sweep_config import split_config
    from pipeline.tune import plan_trial

    out = sweep_run["out"]
    rows = _summary(out)
    base, sweep = split_config(load_config(CONFIG, SWEEP))
    manifest, faces = prepare_bank(data_config(base), sweep_run["bank"], generate=False)
    by_batch = {}
    for row in rows:
        assert row["status"] in ("ok", "adjusted_memory", "skipped_memory"), row  # 1 epoch: none stops early
        # the gate's prediction for this trial's own point, recomputed here from the bank's sizes
        _, plan = plan_trial(base, {"window": int(row["window"]), "batch_size": int(row["batch_size"]),
                                    **{k: float(row[k]) for k in ("rec", "motion", "appearance")}},
                             int(manifest.num_vertices), len(faces), sweep)
        assert (row["memory_decision"], float(row["predicted_memory_gb"])) == (
            plan.status, pytest.approx(plan.predicted_gb, abs=1e-3)), row
        assert row["memory_limit_gb"] == "1.2"
        by_batch.setdefault((row["window"], row["batch_size"]), row)
    skipped = by_batch[("8", "4096")]
    assert skipped["status"] == "skipped_memory" and skipped["run_batch_size"] == "" and skipped["best_pmd_unseen"] == ""
    assert not list((out / "trials").glob(f"*{skipped['trial_id']}*")), "a skipped trial was launched"
    adjusted = by_batch[("8", "64")]
    assert adjusted["memory_decision"] == "adjusted_memory"
    assert adjusted["status"] == "adjusted_memory"  # 1 epoch: it cannot have been stopped early
    assert int(adjusted["run_batch_size"]) * int(adjusted["grad_accumulation"]) == 64
    assert float(adjusted["predicted_memory_gb"]) <= 1.2 < float(adjusted["requested_memory_gb"])
    client, _, children = _runs(out)
    child = next(c for c in children if c.data.tags["trial_id"] == adjusted["trial_id"])
    # measured and scored by the trial's training itself: the values its rank 0 logged to MLflow
    # (the summary has them through Tune's results, another path)
    peak = [m.value for m in client.get_metric_history(child.info.run_id, "peak_memory_gb")]
    pmds = [m.value for m in client.get_metric_history(child.info.run_id, "pmd_unseen")]
    assert len(peak) == len(pmds) == 1, (peak, pmds)
    assert float(adjusted["measured_memory_gb"]) == pytest.approx(peak[0], abs=1e-3)
    assert float(adjusted["best_pmd_unseen"]) == pytest.approx(min(pmds), abs=1e-3)
    # it ran at the adjusted batch, never at 64: the child run's config says so
    assert child.data.params["train.batch_size"] == adjusted["run_batch_size"]
    assert child.data.params["train.grad_accumulation"] == adjusted["grad_accumulation"]
    assert child.data.tags["requested_batch_size"] == "64"


@pytest.mark.slow
@pytest.mark.ray
def test_mlflow_parent_and_child_runs_are_comparable(sweep_run):
    out = sweep_run["out"]
    client, parents, children = _runs(out)
    assert len(parents) == 1 and parents[0].info.status == "FINISHED"
    parent = parents[0]
    assert len(children) == 3
    rows = {r["trial_id"]: r for r in _summary(out)}
    for child in children:
        row = rows[child.data.tags["trial_id"]]
        assert child.data.tags["status"] == row["status"]
        # never left RUNNING: trained trials FINISHED, the skipped one KILLED (MLflow has no "skipped")
        assert child.info.status == {"ok": "FINISHED", "adjusted_memory": "FINISHED",
                                     "skipped_memory": "KILLED"}[row["status"]], (row, child.info)
        assert "predicted_memory_gb" in child.data.tags and "loss.rec" in child.data.params
        if row["status"] != "skipped_memory":
            history = client.get_metric_history(child.info.run_id, "pmd_unseen")
            assert [m.step for m in history] == [1], row  # the trial's one epoch, logged by its training
            # one value per run for the compare view: the trial's best epoch (the lowest PMD its training
            # logged, not only what Tune passed on), its predicted memory
            assert child.data.metrics["best_pmd_unseen"] == pytest.approx(min(m.value for m in history), abs=1e-3)
            assert child.data.metrics["best_pmd_unseen"] == pytest.approx(float(row["best_pmd_unseen"]), abs=1e-3)
            assert child.data.metrics["predicted_memory_gb"] == pytest.approx(float(row["predicted_memory_gb"]), abs=1e-3)
    best = [c for c in children if c.data.tags.get("best") == "true"]
    assert len(best) == 1 and parent.data.tags["best_run_id"] == best[0].info.run_id
    lowest = min(float(r["best_pmd_unseen"]) for r in rows.values()
                 if r["best_pmd_unseen"] and r["status"] in ("ok", "adjusted_memory", "early_stopped"))
    assert best[0].data.metrics["best_pmd_unseen"] == pytest.approx(lowest, abs=1e-3), "the best trial is not the lowest"
    assert [a.path for a in client.list_artifacts(parent.info.run_id)] == ["summary.csv"]


def _tables(output: str) -> list[tuple[str, dict]]:
    """The trial tables a sweep printed: (heading, {trial id: {column: cell}})."""
    tables, lines = [], output.splitlines()
    for i, line in enumerate(lines):
        if line.startswith("== sweep "):
            rows, header = {}, None
            for row in lines[i + 1:]:
                if row.startswith("| trial "):
                    header = [c.strip() for c in row.strip("|").split("|")]
                elif header and row.startswith("| "):
                    cells = [c.strip() for c in row.strip("|").split("|")]
                    rows[cells[0]] = dict(zip(header, cells))
                elif header and row.startswith("+-") and rows:
                    break
            tables.append((line, rows))
    return tables


@pytest.mark.slow
@pytest.mark.ray
def test_sweep_console_shows_a_live_trial_table_then_the_summary_table(sweep_run):
    code, first = sweep_run["first"]
    live = _tables(first)
    assert live, first[-3000:]
    assert any(row["status"] == "running" and row["pred GB"] for _, rows in live for row in rows.values()), live
    assert "Trial status:" not in first and "Result for " not in first  # Tune's own console is not printed
    heading, final = _tables(sweep_run["second"])[-1]
    summary = {r["trial_id"]: r for r in _summary(sweep_run["out"])}
    assert heading.startswith("== sweep tiny_sweep: 3 trials ("), heading
    assert set(final) == set(summary)
    for trial_id, row in summary.items():
        shown = final[trial_id]
        assert shown["status"] == row["status"] and shown["T"] == row["window"]
        assert float(shown["rec"]) == pytest.approx(float(row["rec"]), rel=5e-3)
        if row["best_pmd_unseen"]:
            assert float(shown["best PMD"]) == pytest.approx(float(row["best_pmd_unseen"]), rel=1e-3)
        else:
            assert shown["best PMD"] == "" and shown["batch"] == f"{row['batch_size']} (skip)"
    # printed when something changed, not every few seconds: a log stays readable
    assert len(live) <= 4 * len(summary) + 4, [h for h, _ in live]
