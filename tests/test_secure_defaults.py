"""Secure defaults that need no cluster: checkpoints never unpickle code, outputs stay inside
`--out`, our MLflow server refuses to listen on every interface and keeps a consistent backup.

(What listens where on a real Ray cluster and the token check: tests/test_cluster_security.py; the cluster
config's security settings: tests/test_cluster_config.py.)
"""

from __future__ import annotations

import os
import sqlite3
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
import yaml

from aniformer.checkpoint import KEYS, load_checkpoint, save_checkpoint
from aniformer.errors import UserError
from aniformer.model import AniFormer, AniFormerConfig

ROOT = Path(__file__).resolve().parents[1]
MARKER = "aniformer-pickle-ran"


class Payload:
    """Unpickling this runs code: it creates a marker file (a harmless stand-in for anything)."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (Path.touch, (self.marker,))


def tiny_checkpoint(path: Path) -> Path:
    torch.manual_seed(0)
    cfg = AniFormerConfig(channels=(16,), extractor_channels=(8, 16), heads=2, window=3)
    model = AniFormer(cfg)
    optimizer = torch.optim.Adam(model.parameters())
    scheduler = torch.optim.lr_scheduler.MultiStepLR(optimizer, [1])
    data = yaml.safe_load((ROOT / "configs/tiny.yaml").read_text())["data"]
    return save_checkpoint(path, config={"data": data, "model": {"name": "aniformer", **cfg.to_dict()}},
                           model=model, optimizer=optimizer, scheduler=scheduler, epoch=1, step=1)


# ------------------------------------------------------------------ checkpoints: weights_only


def test_a_checkpoint_carrying_a_pickled_object_is_refused_without_running_it(tmp_path):
    good = tiny_checkpoint(tmp_path / "good.pt")
    state = torch.load(good, weights_only=True)  # the real thing is plain data
    marker = tmp_path / MARKER
    state["config"] = {"model": {"name": "aniformer"}, "extra": Payload(marker)}  # every key present, one poisoned
    evil = tmp_path / "evil.pt"
    torch.save(state, evil)
    assert set(KEYS) <= set(state)
    with pytest.raises(UserError, match="not a readable checkpoint"):
        load_checkpoint(evil)
    assert not marker.exists(), "loading the checkpoint executed code from it"
    assert load_checkpoint(good)["epoch"] == 1


def test_the_checkpoint_loader_keeps_weights_only():
    """`load_checkpoint` is the one loader every job uses; it must keep `weights_only=True`."""
    import ast

    import aniformer.checkpoint as module

    calls = [node for node in ast.walk(ast.parse(Path(module.__file__).read_text()))
             if isinstance(node, ast.Call) and getattr(node.func, "attr", None) == "load"
             and getattr(node.func.value, "id", None) == "torch"]
    assert calls and all(any(k.arg == "weights_only" and getattr(k.value, "value", None) is True for k in c.keywords)
                         for c in calls)


# ------------------------------------------------------------------ outputs stay inside --out


def _tree(root: Path) -> dict[str, bytes | str]:
    found = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            path = Path(dirpath) / name
            rel = str(path.relative_to(root))
            found[rel] = f"-> {os.readlink(path)}" if path.is_symlink() else (path.read_bytes() if path.is_file() else "dir")
    return found


def test_animate_writes_only_inside_out_whatever_the_input_names(tmp_path, monkeypatch):
    """Driving files named `..x.obj`, `x y.obj`, a symlinked frame and a symlinked directory, and
    an `--out` spelled with `..`: every file written lies inside the resolved `--out`."""
    from aniformer.cli.exits import run
    from jobs.animate import main

    ckpt = tiny_checkpoint(tmp_path / "ckpt" / "best.pt")
    sphere = trimesh.creation.icosphere(subdivisions=1)
    vertices = (sphere.vertices * [0.2, 0.12, 0.85]).astype(np.float32)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    real = elsewhere / "real_frame.obj"
    trimesh.Trimesh(vertices * 1.01, sphere.faces, process=False).export(real)
    driving = elsewhere / "clip"
    driving.mkdir()
    for k, name in enumerate(["..frame_0.obj", "frame 1.obj", "frame_2..obj", "-frame_3.obj"]):
        trimesh.Trimesh(vertices + 0.01 * k, sphere.faces, process=False).export(driving / name)
    (driving / "frame_4.obj").symlink_to(real)
    (tmp_path / "link_to_clip").symlink_to(driving, target_is_directory=True)
    target = tmp_path / "target.obj"
    trimesh.Trimesh(vertices, sphere.faces, process=False).export(target)
    (tmp_path / "work").mkdir()
    monkeypatch.chdir(tmp_path / "work")

    before = _tree(tmp_path)
    run(main, ["--checkpoint", str(ckpt), "--target", str(target), "--driving", str(tmp_path / "link_to_clip"),
               "--out", "../work/sub/../anim", "--preview-frames", "2", "--no-progress", "--device", "cpu",
               "--force"])  # an untrained model and an ellipsoid: the self-check refuses the result
    after = _tree(tmp_path)
    out = (tmp_path / "work" / "anim").resolve()
    changed = {k for k in after if before.get(k) != after[k]} | (before.keys() - after.keys())
    outside = [k for k in changed if not (tmp_path / k).resolve().is_relative_to(out)
               and not (tmp_path / k).resolve() == out]
    assert outside == [], f"animate wrote outside --out: {outside}"
    # output names never come from input names ("..frame_0.obj" is a hidden file: not a frame)
    assert sorted(p.name for p in (out / "frames").iterdir()) == [f"frame_{k:04d}.obj" for k in range(4)]


def test_jobs_refuse_a_job_name_that_leaves_out(tmp_path, monkeypatch):
    """`--name` names directories under OUT (OUT/ray/NAME for training, OUT/tune/NAME and
    OUT/trials/NAME-<trial> for sweeps, OUT/runs/<variant> + NAME-<variant> for ablations); `../x` or
    an absolute name would put Ray's files outside. Refused before Ray starts."""
    import importlib

    import pipeline.cluster

    def no_ray():
        raise AssertionError("started Ray with a job name that leaves --out")

    monkeypatch.setattr(pipeline.cluster, "connect", no_ray)
    for job, config in (("train", "tiny.yaml"), ("sweep", "sweep_tiny.yaml"), ("ablate", "ablation.yaml")):
        main = importlib.import_module(f"jobs.{job}").main
        for name in ("../../escaped", str(tmp_path / "abs"), ".."):
            with pytest.raises(UserError, match="--name"):
                main(["--config", str(ROOT / "configs" / config), "--out", str(tmp_path / job), "--name", name])
    assert not (tmp_path.parent / "escaped").exists() and not (tmp_path / "abs").exists()


# ------------------------------------------------------------------ our MLflow server


def test_mlflow_server_refuses_all_interfaces_unless_asked():
    from pipeline.mlflow_server import check_host, server_command

    for wildcard in ("0.0.0.0", "::", "[::]"):
        with pytest.raises(UserError, match="every interface"):
            check_host(wildcard, allow_all=False)
    assert check_host("0.0.0.0", allow_all=True) == "0.0.0.0"
    assert check_host("10.0.1.23", allow_all=False) == "10.0.1.23"
    with pytest.raises(UserError, match="not an IP address"):
        check_host("example.com", allow_all=False)
    cmd = server_command("127.0.0.1", 5000, Path("/s"), "/s/artifacts", auth=True)
    assert cmd[cmd.index("--host") + 1] == "127.0.0.1" and cmd[-2:] == ["--app-name", "basic-auth"]
    assert cmd[cmd.index("--backend-store-uri") + 1] == "sqlite:////s/mlflow.db"


def test_mlflow_store_backup_is_a_consistent_copy_and_restores(tmp_path):
    from pipeline.mlflow_server import backup, fetch

    store, dest = tmp_path / "store", tmp_path / "backup"
    store.mkdir()
    with sqlite3.connect(store / "mlflow.db") as db:
        db.execute("create table runs (name text)")
        db.executemany("insert into runs values (?)", [("tiny",), ("sweep",)])
    writer = sqlite3.connect(store / "mlflow.db")  # a writer holding an open transaction
    writer.execute("begin immediate")
    writer.execute("insert into runs values ('uncommitted')")
    backup(store, str(dest))
    writer.rollback()
    writer.close()
    restored = tmp_path / "restored.db"
    assert fetch(str(dest), "mlflow.db", restored)
    with sqlite3.connect(restored) as db:
        assert sorted(n for (n,) in db.execute("select name from runs")) == ["sweep", "tiny"]
    assert not fetch(str(tmp_path / "nothing"), "mlflow.db", tmp_path / "none.db")
