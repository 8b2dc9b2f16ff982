"""A motion library on disk (jobs/retarget.py): the targets and clips of its two folders, and what a run reports:
OUT/summary.csv (a row per pair), one line per finished pair, the run's MLflow run.
"""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass
from pathlib import Path

from aniformer.errors import UserError
from aniformer.io.files import atomic_path, natural_key
from aniformer.io.mesh import GLTF_SUFFIXES, MESH_SUFFIXES

COLUMNS = ("target", "clip", "status", "frames", "seconds", "fit_mm", "self_check")


@dataclass(frozen=True)
class ClipSource:
    """Where a clip of the library comes from: a folder of frames or a glTF file, and for a glTF of several
    animations the one it is (its index, as jobs/animate.py's ``--animation`` takes it)."""

    path: str
    animation: str | None = None


def find_library(targets: str, clips: str) -> tuple[dict[str, str], dict[str, str]]:
    """({target stem: path}, {clip name: its `ClipSource`}) of the folders ``targets`` and ``clips``, in natural
    order: a sub-folder of frames is a clip of its name, a glTF file a clip of its stem, or with several
    animations one clip per animation (``<stem>_<animation name>``). `UserError` for an empty or missing folder,
    or two targets or clips of one name (their outputs would collide)."""
    targets_dir, clips_dir = Path(targets).expanduser(), Path(clips).expanduser()
    for flag, folder in (("--targets", targets_dir), ("--clips", clips_dir)):
        if not folder.is_dir():
            raise UserError(f"{flag} {folder}: not a folder")
    targets = {}
    for path in sorted(targets_dir.iterdir(), key=lambda p: natural_key(p.name)):
        if path.is_file() and path.suffix.lower() in MESH_SUFFIXES:
            if path.stem in targets:
                raise UserError(f"--targets: {targets[path.stem]} and {path} have one stem, their outputs would "
                                "share OUT/<stem>/: rename one")
            targets[path.stem] = str(path.resolve())
    clips = {}
    for path in sorted(clips_dir.iterdir(), key=lambda p: natural_key(p.name)):
        if path.name.startswith(".") or not (path.is_dir() or path.suffix.lower() in GLTF_SUFFIXES):
            continue
        for name, source in _clips_of(path):
            if name in clips:
                raise UserError(f"--clips: {clips[name].path} and {path} both give clip {name}, their outputs would "
                                f"share OUT/<target>/{name}/: rename one")
            clips[name] = source
    if not targets:
        raise UserError(f"--targets {targets_dir}: no mesh files ({', '.join(MESH_SUFFIXES)})")
    if not clips:
        raise UserError(f"--clips {clips_dir}: no clips (a sub-folder of frames, or an animated .glb/.gltf, each)")
    return targets, clips


def _clips_of(path: Path) -> list[tuple[str, ClipSource]]:
    """(name, source) of the clips a folder or glTF file in ``--clips`` gives."""
    if path.is_dir():
        return [(path.name, ClipSource(str(path.resolve())))]
    from aniformer.io.gltf_scene import animation_names

    names = animation_names(path)
    if len(names) < 2:
        return [(path.stem, ClipSource(str(path.resolve())))]
    safe = [re.sub(r"[^\w.-]+", "_", name).strip("._") for name in names]
    return [(f"{path.stem}_{name if name and safe.count(name) == 1 else f'{name}_{k}'.strip('_')}",
             ClipSource(str(path.resolve()), str(k))) for k, name in enumerate(safe)]


def write_summary(path: Path, rows: list[dict]) -> None:
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as file:
        writer = csv.DictWriter(file, COLUMNS, extrasaction="ignore")
        writer.writeheader()
        writer.writerows({column: row.get(column, "") for column in COLUMNS} for row in rows)


def pair_line(row: dict) -> str:
    """One line per finished pair."""
    where = f"{row['target']} x {row['clip']}"
    if row["status"] == "ok":
        seconds = "earlier run" if row["seconds"] == "" else f"{row['seconds']:.1f} s"
        fit = f", fit {row['fit_mm']} mm" if row["fit_mm"] else ""
        return f"ok       {where}: {row['frames']} frames ({seconds}){fit}, self-check {row['self_check']}"
    return f"{row['status']:<8} {where}: {row['self_check']}"


def log_run(out: Path, params: dict, experiment: str, rows: list[dict], seconds: float, done_now: int) -> str:
    """The MLflow run ``retarget-<OUT name>`` of this output (a rerun continues it): the job's ``params``,
    summary.csv, per-pair metrics (frames, seconds, fit error) and the job's counts; its id."""
    from pipeline.tracking import quiet_mlflow, start_job_run

    quiet_mlflow()
    tracker = start_job_run(f"retarget-{out.name}", params, experiment, out=out)
    with tracker.ended():
        metrics = {f"pairs_{status}": sum(row["status"] == status for row in rows)
                   for status in ("ok", "refused", "error")}
        if done_now:  # a rerun that found every pair complete keeps the rate of the run that did them
            metrics["pairs_per_s"] = done_now / seconds
        for row in rows:
            key = re.sub(r"[^\w./ -]", "_", f"pair/{row['target']}/{row['clip']}")
            metrics |= {f"{key}/{name}": float(row[name]) for name in ("frames", "seconds", "fit_mm")
                        if row.get(name) not in (None, "")}
        tracker.log_metrics(metrics, step=0)
        tracker.log_artifact(out / "summary.csv")  # replaced by a rerun's (log_table would append to it)
    return tracker.run_id
