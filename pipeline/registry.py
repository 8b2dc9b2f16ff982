"""The best model of a training run as a registered MLflow model, and checkpoints named by model URI.

jobs/train.py logs its run's best checkpoint as the MLflow model `model` of the run (`log_best_model`:
an `mlflow.pyfunc` model around the checkpoint file, with the run config as metadata, a signature and
an input example) and registers it as a new version of the registered model `aniformer`
(`--register-as NAME`, `--no-register`). `resolve_checkpoint` turns a job's ``--checkpoint`` into a local
file: a checkpoint file or directory as it is, an MLflow run id (`pipeline.tracking.download_run_checkpoint`),
or `models:/NAME/latest`, `models:/NAME/VERSION` and `models:/NAME@ALIAS` (`download_model_checkpoint`: the
version's checkpoint artifact). The caller loads it with `aniformer.checkpoint.model_from_checkpoint`
(`torch.load(weights_only=True)`).

`mlflow.pyfunc.load_model(uri).predict(inputs)` is the model's forward pass on a batch of windows.
`inputs` is a dict of numpy arrays (a tensor-based signature):

    driving  (B, T, V1, 3) float32  T driving frames, T = the model's window; metres, z up
    target   (B, V2, 3)    float32  the meshes to animate
    faces    (F, 3)        int64    the triangles of the topology; only models with `output: transfer`

It returns (B, T', V2, 3) float32: each target in each driving pose (T' = T, or 1 for a regression
head). Meshes go in as training fed them: each bounding-box centred when the checkpoint's
`data.center` is `mesh` (the default). jobs/animate.py slides such windows over a whole sequence.
Loading it needs this project installed (the wrapper and the model are its code).
"""

from __future__ import annotations

import contextlib
import os
import re
from importlib.metadata import requires
from pathlib import Path

import mlflow.pyfunc
import numpy as np

from aniformer.errors import UserError
from pipeline.tracking import RUN_ID, Tracker, download_run_checkpoint, existing_store, quiet_mlflow

MODEL_NAME = "model"  # the logged model's name in its run
CHECKPOINT_KEY = "checkpoint"  # the checkpoint's key among the pyfunc model's artifacts
MODEL_URI = re.compile(r"models:/[^/@]+(/[^/]+|@[^/]+)/?")
# MLflow's progress bar of artifact copies: a bar per one-file copy, noise in a job's console.
NO_PROGRESS_BAR = {"MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR": "false"}


class AniFormerPyfunc(mlflow.pyfunc.PythonModel):
    """An AniFormer checkpoint as an MLflow pyfunc model: `predict` is its forward pass (module doc)."""

    # MLflow's flag to skip its type-hint validation (and its warning that `predict` has no hints, on
    # every import): it knows no dict of arrays, and the signature logged with the model checks the input.
    _skip_type_hint_validation = True

    def load_context(self, context) -> None:
        from aniformer.checkpoint import model_from_checkpoint

        self.model, _ = model_from_checkpoint(context.artifacts[CHECKPOINT_KEY])

    def predict(self, context, model_input, params=None) -> np.ndarray:
        import torch

        faces = model_input.get("faces")
        with torch.inference_mode():
            out = self.model(torch.from_numpy(model_input["driving"]), torch.from_numpy(model_input["target"]),
                             None if faces is None else torch.from_numpy(faces))
        return out.numpy()


def _needs_faces(model) -> bool:
    return getattr(model.config, "output", "absolute") == "transfer"


def signature(model):
    """The tensor signature of `model`'s forward: any batch and vertex count, its window T."""
    from mlflow.models import ModelSignature
    from mlflow.types.schema import Schema, TensorSpec

    window = model.config.window
    inputs = [TensorSpec(np.dtype(np.float32), (-1, window, -1, 3), "driving"),
              TensorSpec(np.dtype(np.float32), (-1, -1, 3), "target")]
    if _needs_faces(model):
        inputs.append(TensorSpec(np.dtype(np.int64), (-1, 3), "faces"))
    frames = len(range(window)[model.config.output_frames()])
    return ModelSignature(Schema(inputs), Schema([TensorSpec(np.dtype(np.float32), (-1, frames, -1, 3))]))


def input_example(model, topology: str) -> dict[str, np.ndarray]:
    """One window of the checkpoint's Anny topology: a body at rest driving another body, each centred."""
    from aniformer.geometry import center_bbox
    from aniformer.synth.bodies import BodyModel, sample_identities

    body = BodyModel(topology)
    rest = center_bbox(body.pose(sample_identities(2, seed=0), np.zeros((2, len(body.bone_labels), 3))))
    example = {"driving": np.repeat(rest[:1, None], model.config.window, axis=1), "target": rest[1:]}
    if _needs_faces(model):
        example["faces"] = body.faces
    return example


def project_requirements() -> list[str]:
    """The installed project's own dependencies: the model is its code. Given to log_model explicitly,
    which would otherwise load the model in a subprocess to infer them."""
    return [r for r in requires("aniformer") or [] if "extra ==" not in r]


@contextlib.contextmanager
def environment(**values: str):
    """`os.environ` with `values` inside the block only: MLflow reads its settings at each call, and a
    process-wide `mlflow.set_tracking_uri` would outlive the job's call (a test session's other stores)."""
    previous = {name: os.environ.get(name) for name in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for name, value in previous.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def _first_line(e: Exception) -> str:
    return (str(e).splitlines()[0] if str(e) else type(e).__name__)[:200]


def check_registered_name(name: str) -> str:
    """A name `models:/NAME/...` can name (checked before training, not after it)."""
    if not re.fullmatch(r"[^/@:\s]+", name):
        raise UserError(f"--register-as {name!r}: a registered model name has no '/', '@', ':' or spaces")
    return name


def log_best_model(tracker: Tracker, checkpoint: Path, register_as: str | None) -> str:
    """Log `checkpoint` as the MLflow model of `tracker`'s run and, unless `register_as` is None,
    register it as a new version of that registered model. Returns the model's URI
    (`models:/NAME/VERSION` when registered)."""
    import mlflow

    from aniformer.checkpoint import model_from_checkpoint

    model, state = model_from_checkpoint(checkpoint)
    quiet_mlflow()
    try:
        with environment(MLFLOW_TRACKING_URI=tracker.uri, **NO_PROGRESS_BAR), mlflow.start_run(run_id=tracker.run_id):
            info = mlflow.pyfunc.log_model(
                name=MODEL_NAME, python_model=__file__, artifacts={CHECKPOINT_KEY: str(checkpoint)},
                signature=signature(model), input_example=input_example(model, state["config"]["data"]["topology"]),
                metadata={"config": state["config"], "epoch": state["epoch"]},
                pip_requirements=project_requirements(),
                registered_model_name=register_as)
    except Exception as e:  # unreachable server, a registry refusing the name: one line, best.pt is kept
        raise UserError(f"logging {checkpoint} as an MLflow model failed ({_first_line(e)}); "
                        "the checkpoint itself is saved") from None
    if register_as is None:
        return info.model_uri
    return f"models:/{register_as}/{info.registered_model_version}"


def resolve_checkpoint(reference: str, scratch: Path) -> Path:
    """A job's ``--checkpoint`` as a local checkpoint file or directory: a registered model URI's checkpoint
    (`download_model_checkpoint`), a file or directory that exists as it is, else an MLflow run id's or
    ``runs:/`` URI's best checkpoint (`pipeline.tracking.download_run_checkpoint`); downloads go into `scratch`."""
    if reference.startswith("models:/"):
        return download_model_checkpoint(reference, scratch)
    path = Path(os.path.expanduser(reference))
    if path.exists():
        return path
    match = RUN_ID.fullmatch(reference)
    if match is None:
        raise UserError(f"checkpoint not found: {reference} (give a checkpoint file, an MLflow run id or a "
                        "registered model URI)")
    return download_run_checkpoint(match.group(1), scratch)


def download_model_checkpoint(reference: str, scratch: Path) -> Path:
    """The checkpoint artifact of registered model version `reference` (models:/NAME/VERSION, models:/NAME/latest
    or models:/NAME@ALIAS), downloaded into `scratch/model`."""
    if MODEL_URI.fullmatch(reference) is None:
        raise UserError(f"{reference}: not a registered model URI (models:/NAME/VERSION, models:/NAME/latest "
                        "or models:/NAME@ALIAS)")
    quiet_mlflow()
    import mlflow
    from mlflow.models import Model

    uri = existing_store(reference)
    try:
        with environment(**NO_PROGRESS_BAR):
            local = Path(mlflow.artifacts.download_artifacts(artifact_uri=reference.rstrip("/"), tracking_uri=uri,
                                                             registry_uri=uri, dst_path=str(scratch / "model")))
        checkpoint = Model.load(local).flavors["python_function"]["artifacts"][CHECKPOINT_KEY]["path"]
    except Exception as e:  # no such model or version, not an AniFormer model, unreachable server: one line
        raise UserError(f"{reference}: cannot load this registered model from {uri} ({_first_line(e)})") from None
    return local / checkpoint


# The model this file defines when MLflow loads it as a model from code: log_best_model logs the file
# itself as the model's code, so loading it unpickles nothing.
mlflow.models.set_model(AniFormerPyfunc())
