"""System test, jobs: the tiny training job through `ray job submit` and a tiny sweep submitted as soon as
the training job's mesh bank exists, both run at once on the real local Ray cluster (the session's `jobs`
and `cluster` fixtures, tests/conftest.py and tests/cluster_helpers.py) and tracked by our MLflow server;
and a symlink planted in the training job's --out. Each test sets up what it needs through fixtures, so
any one runs alone or in any order.
"""

from __future__ import annotations

import csv

import pytest
from cluster_helpers import ROOT, TRAIN, TRIALS, mlflow_runs, tags

pytestmark = pytest.mark.slow


def test_training_job_submitted_to_the_cluster(cluster, jobs):
    status, logs = jobs.train
    assert status == "SUCCEEDED", logs[-5000:]
    out = jobs.train_out
    import torch

    from aniformer.checkpoint import load_checkpoint
    from aniformer.cli.args import load_config
    from pipeline.run_spec import RunSpec

    best, last = load_checkpoint(out / "best.pt"), load_checkpoint(out / "last.pt")
    assert best["config"] == RunSpec.from_config(load_config(ROOT / "configs/tiny.yaml", TRAIN)).to_dict()
    # one epoch: the best is the last, weight for weight
    assert best["epoch"] == last["epoch"] == 1 and best["model"].keys() == last["model"].keys()
    assert all(torch.equal(best["model"][k], last["model"][k]) for k in best["model"])
    # Logged to the server through the nodes' environment (no runtime_env), metrics by the trainer.
    _, runs = mlflow_runs(cluster)
    (run,) = [r for r in runs if r["info"]["run_name"] == "tiny"]
    assert run["info"]["status"] == "FINISHED"
    assert {m["key"] for m in run["data"].get("metrics", [])} >= {"pmd_unseen", "loss"}


def test_a_symlink_planted_in_out_is_replaced_not_written_through(cluster, jobs):
    last = jobs.train_out / "last.pt"
    assert last.exists(), "the training job did not run"
    assert (cluster.root / "outside.txt").read_bytes() == b"untouched" and not last.is_symlink()


def test_sweep_job_submitted_to_the_cluster(cluster, jobs):
    assert jobs.sweep is not None, "not submitted: the training job made no mesh bank"
    status, logs = jobs.sweep
    assert status == "SUCCEEDED", logs[-5000:]
    assert f"== sweep sweep: {TRIALS} trials (" in logs and "| trial " in logs, logs[-5000:]  # its table, in the job's log
    rows = list(csv.DictReader((jobs.sweep_out / "summary.csv").open()))
    assert len(rows) == TRIALS and all(r["status"] in ("ok", "early_stopped", "adjusted_memory") for r in rows), rows
    _, runs = mlflow_runs(cluster)
    (parent,) = [r for r in runs if r["info"]["run_name"] == "sweep"]
    children = [r for r in runs if tags(r).get("mlflow.parentRunId") == parent["info"]["run_id"]]
    assert parent["info"]["status"] == "FINISHED" and len(children) == TRIALS

