"""The best model as a registered MLflow model (pipeline/registry.py), on an embedded sqlite store.

A tiny untrained checkpoint with the shipped model's `output: transfer` (so the pyfunc input has
faces) is logged and registered as jobs/train.py does; it is then loaded back by registered name the
way jobs/animate.py and jobs/evaluate.py do, and through `mlflow.pyfunc.load_model`.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from test_animate import TINY_MODEL, animate_main, make_checkpoint

from aniformer.checkpoint import model_from_checkpoint
from aniformer.cli.exits import run
from aniformer.io.mesh import write_obj


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> dict:
    """A store holding one training run whose best checkpoint is registered as `aniformer` version 1."""
    import mlflow

    from pipeline.registry import log_best_model
    from pipeline.tracking import start_job_run

    root = tmp_path_factory.mktemp("registry")
    store_uri = f"sqlite:///{root / 'mlflow.db'}"
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MLFLOW_TRACKING_URI", store_uri)
        checkpoint = make_checkpoint(root / "run" / "best.pt", output="transfer")
        tracker = start_job_run("train", {"train": {"epochs": 1}}, out=root / "run")
        uri = log_best_model(tracker, checkpoint, "aniformer")
        tracker.end("FINISHED")
    assert mlflow.get_tracking_uri() != store_uri  # logging left no process-wide store behind
    return {"root": root, "checkpoint": checkpoint, "run_id": tracker.run_id, "uri": uri}


@pytest.fixture
def in_store(store, monkeypatch) -> dict:
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{store['root'] / 'mlflow.db'}")
    return store


def downloaded(uri: str, dst: Path):
    """(local directory, MLmodel) of a model URI."""
    import mlflow
    from mlflow.models import Model

    local = mlflow.artifacts.download_artifacts(artifact_uri=uri, dst_path=str(dst))
    return local, Model.load(local)


def posed_window(example: dict, seed: int = 0) -> dict:
    """The model's input example with every driving frame moved differently (a window with motion)."""
    rng = np.random.default_rng(seed)
    driving = example["driving"] + rng.normal(0, 0.02, example["driving"].shape).astype(np.float32)
    return {**example, "driving": driving}


def test_registered_by_name_with_config_signature_and_example(in_store, tmp_path):
    from mlflow import MlflowClient

    assert in_store["uri"] == "models:/aniformer/1"
    client = MlflowClient()
    (version,) = client.search_model_versions("name = 'aniformer'")
    assert version.version == 1 and version.run_id == in_store["run_id"]
    assert client.get_run(version.run_id).info.status == "FINISHED"
    local, meta = downloaded("models:/aniformer/latest", tmp_path)
    assert meta.metadata["config"]["model"]["output"] == "transfer" and meta.metadata["epoch"] == 1
    assert [(s.name, s.shape, str(s.type)) for s in meta.signature.inputs.inputs] == [
        ("driving", (-1, 3, -1, 3), "float32"), ("target", (-1, -1, 3), "float32"), ("faces", (-1, 3), "int64")]
    example = meta.load_input_example(local)
    assert example["driving"].shape == (1, 3, 369, 3) and example["target"].shape == (1, 369, 3)
    assert example["faces"].shape == (734, 3)


def test_pyfunc_predict_is_the_models_forward(in_store):
    import mlflow

    pyfunc = mlflow.pyfunc.load_model("models:/aniformer/latest")
    inputs = posed_window(pyfunc.input_example)
    predicted = pyfunc.predict(inputs)
    model, _ = model_from_checkpoint(in_store["checkpoint"])
    with torch.no_grad():
        direct = model(*(torch.from_numpy(inputs[k]) for k in ("driving", "target", "faces"))).numpy()
    assert predicted.shape == (1, 3, 369, 3) and predicted.dtype == np.float32
    np.testing.assert_allclose(predicted, direct, rtol=0, atol=1e-6)
    assert np.abs(predicted - inputs["target"][:, None]).max() > 1e-3  # the target was moved, not copied
    with pytest.raises(Exception, match="faces"):  # the signature asks for the faces of a transfer model
        pyfunc.predict({k: inputs[k] for k in ("driving", "target")})


def test_animate_by_registered_name_as_from_the_checkpoint_file(in_store, tmp_path):
    import mlflow

    example = posed_window(mlflow.pyfunc.load_model("models:/aniformer/1").input_example)
    for k, frame in enumerate(np.concatenate([example["driving"][0], example["driving"][0][::-1]])):
        write_obj(tmp_path / "driving" / f"frame_{k}.obj", frame, example["faces"])
    write_obj(tmp_path / "target.obj", example["target"][0], example["faces"])
    frames = []
    for k, checkpoint in enumerate(("models:/aniformer/latest", "models:/aniformer/1", str(in_store["checkpoint"]))):
        out = tmp_path / f"anim{k}"
        animate_main(["--checkpoint", checkpoint, "--target", tmp_path / "target.obj", "--driving", tmp_path / "driving",
                      "--out", out, "--no-glb", "--preview-frames", 0, "--no-progress", "--force"])
        assert json.loads((out / "animation.json").read_text())["checkpoint"] == checkpoint
        frames.append([p.read_text() for p in sorted((out / "frames").glob("*.obj"))])
    assert len(frames[0]) == 6 and frames[0] == frames[1] == frames[2]


@pytest.mark.parametrize("job,spec", [("animate", "models:/nosuch/latest"), ("animate", "models:/aniformer/7"),
                                      ("evaluate", "models:/nosuch/1"), ("animate", "models:/aniformer")])
def test_a_missing_registered_model_is_one_line(in_store, tmp_path, capsys, job, spec):
    from jobs.evaluate import main as evaluate_main

    write_obj(tmp_path / "mesh.obj", np.eye(3, dtype=np.float32), np.array([[0, 1, 2]]))
    argv = (["--target", tmp_path / "mesh.obj", "--driving", tmp_path / "mesh.obj"] if job == "animate" else [])
    main = animate_main if job == "animate" else evaluate_main
    with pytest.raises(SystemExit) as exc:
        run(main, [str(a) for a in ["--checkpoint", spec, "--out", tmp_path / "out", *argv]])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and len(err.strip().splitlines()) == 1 and err.startswith(f"error: {spec}"), err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("kind", ["absolute", "regression", "npt"])
def test_the_signature_fits_every_kind_of_model(kind):
    """Models without faces take no faces input; a regression head returns one frame per window."""
    from aniformer.model import AniFormer, AniFormerConfig
    from aniformer.models import NPT, NPTConfig
    from pipeline.registry import signature

    model = (NPT(NPTConfig(extractor_channels=(8, 16), channels=(19, 16), window=3)) if kind == "npt" else
             AniFormer(AniFormerConfig(**TINY_MODEL, head="regression" if kind == "regression" else "constraints")))
    sig = signature(model)
    assert [s.name for s in sig.inputs.inputs] == ["driving", "target"]
    with torch.no_grad():
        out = model(torch.zeros(2, 3, 40, 3), torch.zeros(2, 50, 3))
    (spec,) = sig.outputs.inputs
    assert len(spec.shape) == out.dim() and all(d in (-1, n) for d, n in zip(spec.shape, out.shape))
    assert spec.shape[1] == (1 if kind == "regression" else 3)


def test_log_without_registering(store, tmp_path, monkeypatch):
    from mlflow import MlflowClient

    from pipeline.registry import log_best_model
    from pipeline.tracking import start_job_run

    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    tracker = start_job_run("train", {}, out=tmp_path / "run")
    uri = log_best_model(tracker, store["checkpoint"], None)
    assert uri.startswith("models:/m-") and MlflowClient().search_registered_models() == []
    _, meta = downloaded(uri, tmp_path / "model")
    assert meta.run_id == tracker.run_id
