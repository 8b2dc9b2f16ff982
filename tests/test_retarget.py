"""jobs/retarget.py on the shared local Ray cluster: a library of targets x clips as one job, each foreign mesh
registered once, a broken clip failing alone, a rerun after Ctrl-C resuming, and a pair equal to animate's.

Inputs are small: Anny's 369-vertex topology (the shipped model's), 4-frame clips, one foreign target (a
decimated body) and one foreign clip (a clip's vertices in another order), each registered once (~10 s)."""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
TOPOLOGY = "notoes_collapse3pc"  # the shipped model's


@pytest.fixture(scope="module")
def library(tmp_path_factory, job_main) -> Path:
    """targets/{anny,decimated}.obj, clips/{walk,crouch,shuffled_walk}/ (4 frames each) and clips/walk_glb.glb (the
    walk as a glTF of two animations), as a user has them."""
    import trimesh

    from aniformer.cli.exits import run
    from aniformer.io.mesh import load_mesh
    from aniformer.synth.stream import StreamPairs, _body_model, pose_pairs
    from aniformer.synth.variants import remesh

    root = tmp_path_factory.mktemp("library")
    for split in ("locomotion", "crouch"):
        run(job_main("export_meshes"), ["--stream", TOPOLOGY, "--split", split, "--frames", "4",
                                        "--out", str(root / "export" / split)])
    (root / "targets").mkdir()
    shutil.copy(root / "export" / "locomotion" / "target.obj", root / "targets" / "anny.obj")
    full = _body_model("notoes")  # a body of another topology, decimated: registered as in test_registration
    body = pose_pairs(full, StreamPairs(TOPOLOGY, window=1, seed=5).draws("characters", 0, [0]))[2][0, 0]
    trimesh.Trimesh(*remesh(body, full.faces), process=False).export(root / "targets" / "decimated.obj")
    clips = root / "clips"
    shutil.copytree(root / "export" / "locomotion" / "driving", clips / "walk")
    shutil.copytree(root / "export" / "crouch" / "driving", clips / "crouch")
    from aniformer.animate import driving_files, load_driving
    from aniformer.io.glb import write_glb

    # the walk as one glTF of two animations (the second a copy): a clip each
    with_second_animation(write_glb(clips / "walk_glb.glb", *load_driving(driving_files(clips / "walk")), name="walk"),
                          "walk again")
    order = np.random.default_rng(0).permutation(369)
    (clips / "shuffled_walk").mkdir()
    for frame in sorted((clips / "walk").glob("*.obj")):
        vertices, faces = load_mesh(frame)  # the same clip, its vertices in another order: a foreign topology
        trimesh.Trimesh(vertices[order], np.argsort(order)[faces], process=False).export(
            clips / "shuffled_walk" / frame.name)
    return root


def with_second_animation(path: Path, name: str) -> Path:
    """``path``, a GLB of one animation, with a copy of it named ``name`` added."""
    import struct

    from aniformer.io.glb import read_document, write_glb_file

    gltf, _ = read_document(path)
    data = path.read_bytes()
    copy = json.loads(json.dumps(gltf["animations"][0]))
    copy["name"] = name
    gltf["animations"].append(copy)
    return write_glb_file(path, gltf, [data[20 + struct.unpack_from("<I", data, 12)[0] + 8:]])


def test_a_gltf_of_several_animations_is_a_clip_each(library):
    from pipeline.motion_library import ClipSource, find_library

    _, clips = find_library(str(library / "targets"), str(library / "clips"))
    glb = str((library / "clips" / "walk_glb.glb").resolve())
    assert clips == {"walk": ClipSource(str((library / "clips" / "walk").resolve())),
                     "crouch": ClipSource(str((library / "clips" / "crouch").resolve())),
                     "shuffled_walk": ClipSource(str((library / "clips" / "shuffled_walk").resolve())),
                     "walk_glb_walk": ClipSource(glb, "0"), "walk_glb_walk_again": ClipSource(glb, "1")}


def retarget_command(targets: Path, clips: Path, out: Path) -> list[str]:
    return [sys.executable, str(ROOT / "jobs" / "retarget.py"), "--targets", str(targets), "--clips", str(clips),
            "--out", str(out), "--no-progress"]


def job_env(ray_address: str, tmp_path: Path) -> dict:
    return {**os.environ, "RAY_ADDRESS": ray_address, "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}"}


def summary_rows(out: Path) -> dict[tuple[str, str], dict]:
    with open(out / "summary.csv", newline="") as file:
        return {(row["target"], row["clip"]): row for row in csv.DictReader(file)}


@pytest.mark.slow
@pytest.mark.ray
def test_a_library_is_one_job_each_foreign_mesh_registered_once_and_a_pair_equals_animate(
        library, ray_address, tmp_path, job_main, monkeypatch):
    """2 targets x 5 clips: every pair ok with animate's outputs, the decimated target and the shuffled clip
    registered exactly once each (the job's registration lines), the walk played from its glTF as from its
    frames, the MLflow run logged; then anny x shuffled_walk by jobs/animate.py alone gives the same frames, GLB
    and record, with the job's kept fit."""
    out = tmp_path / "library_out"
    job = subprocess.run(retarget_command(library / "targets", library / "clips", out),
                         env=job_env(ray_address, tmp_path), capture_output=True, text=True, timeout=600)
    assert job.returncode == 0, job.stderr[-3000:]
    lines = job.stdout.splitlines()
    registered = [line for line in lines if line.startswith("registered ")]
    assert len(registered) == 2, lines
    assert sum(line.startswith("registered target decimated onto Anny") for line in registered) == 1
    assert sum(line.startswith("registered clip shuffled_walk onto Anny") for line in registered) == 1
    assert sum(line.startswith("ok ") for line in lines) == 10 and "10 of 10 ok" in job.stdout
    rows = summary_rows(out)
    assert len(rows) == 10 and {row["status"] for row in rows.values()} == {"ok"}
    for (target, clip), row in rows.items():
        pair = out / target / clip
        assert row["frames"] == "4" and row["self_check"].startswith("trusted")
        assert len(list((pair / "frames").glob("frame_*.obj"))) == 4
        assert (pair / "animation.glb").is_file() and (pair / "preview.gif").is_file()
        assert bool(row["fit_mm"]) == (target == "decimated" or clip == "shuffled_walk")
    assert not [p for p in out.rglob(".*") if p.name != ".lock"]  # no staging left behind
    for target in ("anny", "decimated"):
        for index, clip in enumerate(("walk_glb_walk", "walk_glb_walk_again")):
            played = json.loads((out / target / clip / "animation.json").read_text())["driving_animation"]
            assert (played["index"], played["of"]) == (index, 2)
            for name in sorted(p.name for p in (out / target / "walk" / "frames").iterdir()):
                np.testing.assert_allclose(*(np.loadtxt(out / target / c / "frames" / name, usecols=(1, 2, 3),
                                                        comments=("#", "f")) for c in ("walk", clip)), atol=1e-5)

    from pipeline.tracking import find_job_run

    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    tracker = find_job_run(f"retarget-{out.name}", out=out)
    metrics = tracker.client.get_run(tracker.run_id).data.metrics
    assert metrics["pairs_ok"] == 10 and metrics["pair/decimated/walk/frames"] == 4
    assert "summary.csv" in [a.path for a in tracker.client.list_artifacts(tracker.run_id)]

    from aniformer.cli.exits import run

    alone = tmp_path / "alone"
    run(job_main("animate"), ["--target", str(library / "targets" / "anny.obj"), "--driving",
                              str(library / "clips" / "shuffled_walk"), "--out", str(alone), "--no-progress"])
    pair = out / "anny" / "shuffled_walk"
    frames = sorted(p.name for p in (alone / "frames").iterdir())
    assert frames == sorted(p.name for p in (pair / "frames").iterdir())
    for name in frames:
        assert (alone / "frames" / name).read_bytes() == (pair / "frames" / name).read_bytes(), name
    assert (alone / "animation.glb").read_bytes() == (pair / "animation.glb").read_bytes()
    records = [json.loads((p / "animation.json").read_text()) for p in (alone, pair)]
    # the job kept its fit of the clip (the session's fit cache), and animate alone loaded it
    assert [r["registered"]["driver"].pop("fit_cached") for r in records] == [True, False]
    assert [{k: v for k, v in r.items() if k != "seconds"} for r in records] == [
        {k: v for k, v in records[0].items() if k != "seconds"}] * 2


@pytest.mark.slow
@pytest.mark.ray
def test_the_skinned_transfer_runs_in_the_library_job_as_in_animate(library, ray_address, tmp_path, job_main):
    """--checkpoint skinned: the actors fit Anny's skeleton instead of running a network, and the pair's frames
    and record are the ones jobs/animate.py --checkpoint skinned writes alone."""
    from aniformer.cli.exits import run

    targets, clips = tmp_path / "targets", tmp_path / "clips"
    targets.mkdir()
    shutil.copy(library / "targets" / "anny.obj", targets)
    shutil.copytree(library / "clips" / "crouch", clips / "crouch")
    out = tmp_path / "library_out"
    job = subprocess.run([*retarget_command(targets, clips, out), "--checkpoint", "skinned"],
                         env=job_env(ray_address, tmp_path), capture_output=True, text=True, timeout=600)
    assert job.returncode == 0, job.stderr[-3000:]
    assert "1 of 1 ok" in job.stdout
    alone = tmp_path / "alone"
    run(job_main("animate"), ["--checkpoint", "skinned", "--target", str(targets / "anny.obj"), "--driving",
                              str(clips / "crouch"), "--out", str(alone), "--no-progress"])
    pair = out / "anny" / "crouch"
    for name in sorted(p.name for p in (alone / "frames").iterdir()):
        assert (alone / "frames" / name).read_bytes() == (pair / "frames" / name).read_bytes(), name
    records = [json.loads((p / "animation.json").read_text()) for p in (alone, pair)]
    assert records[0]["model"]["method"] == "skinned transfer" and records[0]["window"] == 4
    assert [{k: v for k, v in r.items() if k != "seconds"} for r in records] == [
        {k: v for k, v in records[0].items() if k != "seconds"}] * 2


@pytest.mark.slow
@pytest.mark.ray
def test_a_broken_clip_fails_alone_and_a_rerun_after_ctrl_c_skips_the_complete_pairs(library, ray_address, tmp_path):
    """Ctrl-C after the first pair: exit 130, what is there is complete. The rerun skips those pairs (their
    files untouched), does the rest, gives the broken clip an error row with its one-line reason, and
    exits 2 naming it."""
    targets, clips, out = tmp_path / "targets", tmp_path / "clips", tmp_path / "out"
    targets.mkdir()
    shutil.copy(library / "targets" / "anny.obj", targets)
    for clip in ("walk", "crouch"):
        shutil.copytree(library / "clips" / clip, clips / clip)
    (clips / "broken").mkdir()
    (clips / "broken" / "frame_0000.obj").write_text("v 0 0 nonsense\nf 1 2 3\n")
    command, env = retarget_command(targets, clips, out), job_env(ray_address, tmp_path)

    job = subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    for line in job.stdout:
        if line.startswith("ok "):
            job.send_signal(signal.SIGINT)
            break
    _, stderr = job.communicate(timeout=120)
    assert job.returncode == 130, stderr[-3000:]
    complete = {p.parent.name: p.stat() for p in out.glob("anny/*/animation.json")}
    assert complete and set(complete) <= {"walk", "crouch"}
    assert not [p for p in out.rglob("*") if p.is_dir() and p.parent.name == "anny" and p.name not in complete
                and not p.name.startswith(".")]  # nothing half-written under a pair's name

    rerun = subprocess.run(command, env=env, capture_output=True, text=True, timeout=600)
    assert rerun.returncode == 2, rerun.stderr[-3000:]
    assert rerun.stderr.strip().splitlines()[-1].startswith("error: 1 of 3 pairs not written (anny x broken: error)")
    assert f"{len(complete)} pairs complete already, {3 - len(complete)} to do" in rerun.stdout
    for clip, stat in complete.items():
        assert f"ok       anny x {clip}: 4 frames (earlier run)" in rerun.stdout
        again = (out / "anny" / clip / "animation.json").stat()
        assert (again.st_ino, again.st_mtime_ns) == (stat.st_ino, stat.st_mtime_ns)  # not recomputed
    rows = summary_rows(out)
    assert [rows["anny", c]["status"] for c in ("walk", "crouch", "broken")] == ["ok", "ok", "error"]
    reason = rows["anny", "broken"]["self_check"]
    assert "broken" in reason and "\n" not in reason and "Traceback" not in reason
    assert not (out / "anny" / "broken").exists()


@pytest.mark.slow
@pytest.mark.ray
def test_workers_killed_mid_job_cost_a_retry_not_the_pairs(library, ray_address, tmp_path, ray_cluster):
    """SIGKILL the worker of the running registration of the foreign clip, and the inference actor's: Ray runs
    the registration again and restarts the actor, which reloads the model; every pair is ok, and the clip
    is registered once as far as the job is concerned."""
    import time

    import trimesh
    from ray.util.state import list_actors, list_tasks

    from aniformer.io.mesh import load_mesh

    targets, clips, out = tmp_path / "targets", tmp_path / "clips", tmp_path / "out"
    targets.mkdir()
    shutil.copy(library / "targets" / "anny.obj", targets)
    shutil.copytree(library / "clips" / "walk", clips / "walk")
    (clips / "shuffled_walk").mkdir()
    for frame in sorted((library / "clips" / "shuffled_walk").glob("*.obj")):
        vertices, faces = load_mesh(frame)  # 1 mm aside: a clip no earlier job has a kept fit of, so it is registered
        trimesh.Trimesh(vertices + [0.001, 0, 0], faces, process=False).export(clips / "shuffled_walk" / frame.name)
    job = subprocess.Popen(retarget_command(targets, clips, out), env=job_env(ray_address, tmp_path),
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    killed, deadline = set(), time.monotonic() + 60
    while len(killed) < 2 and time.monotonic() < deadline and job.poll() is None:
        running = list_tasks(filters=[("func_or_class_name", "=", "register_clip_task"), ("state", "=", "RUNNING")])
        actors = list_actors(filters=[("class_name", "=", "Animator"), ("state", "=", "ALIVE")])
        for what, pid in [("registration", t.worker_pid) for t in running] + [("actor", a.pid) for a in actors]:
            if what not in killed and pid:
                os.kill(pid, signal.SIGKILL)
                killed.add(what)
        time.sleep(0.5)
    stdout, stderr = job.communicate(timeout=300)
    assert killed == {"registration", "actor"}, (killed, stdout)
    assert job.returncode == 0, stderr[-3000:]
    assert stdout.count("registered clip shuffled_walk") == 1
    assert {row["status"] for row in summary_rows(out).values()} == {"ok"} and len(summary_rows(out)) == 2
