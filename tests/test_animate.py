"""Sliding-window animation, the GLB writer, jobs/animate.py end to end and its bad-input handling."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
import yaml

from aniformer.animate import (
    animate_sequence,
    driving_files,
    load_driving,
    natural_key,
    num_windows,
    read_glb,
    window_plan,
    write_glb,
    write_obj,
)
from aniformer.checkpoint import save_checkpoint
from aniformer.cli import UserError, run
from aniformer.mesh import MeshError, center_bbox
from aniformer.model import AniFormer, AniFormerConfig

ROOT = Path(__file__).resolve().parents[1]
TINY_MODEL = dict(channels=(16,), extractor_channels=(8, 16), heads=2, window=3)


def make_checkpoint(path: Path, **model_kw) -> Path:
    """An untrained tiny model saved as a real checkpoint (the pipeline, not the quality, is under test)."""
    torch.manual_seed(0)
    cfg = AniFormerConfig(**{**TINY_MODEL, **model_kw})
    model = AniFormer(cfg)
    optimizer = torch.optim.Adam(model.parameters())
    scheduler = torch.optim.lr_scheduler.MultiStepLR(optimizer, [1])
    data = yaml.safe_load((ROOT / "configs" / "tiny.yaml").read_text())["data"]
    config = {"data": data, "model": {"name": "aniformer", **cfg.to_dict()}}
    return save_checkpoint(path, config=config, model=model, optimizer=optimizer, scheduler=scheduler, epoch=1, step=1)


def body(subdivisions: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """A person-sized ellipsoid (metres, z up)."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    return (sphere.vertices * [0.2, 0.12, 0.85]).astype(np.float32), sphere.faces.astype(np.int64)


def driving_sequence(frames: int = 30) -> tuple[np.ndarray, np.ndarray]:
    """(frames, V, 3): the ellipsoid bending sideways and hopping."""
    v, f = body(2)
    t = np.arange(frames)[:, None] / frames
    bend = 0.3 * np.sin(2 * np.pi * t) * (v[None, :, 2] / 0.85) ** 2
    seq = np.repeat(v[None], frames, 0)
    seq[..., 0] += bend
    seq[..., 2] += 0.1 * np.abs(np.sin(2 * np.pi * t))
    return seq.astype(np.float32), f


def write_driver(directory: Path, frames: int = 30, suffix: str = ".obj") -> Path:
    directory.mkdir(parents=True, exist_ok=True)
    seq, faces = driving_sequence(frames)
    for k, vertices in enumerate(seq):
        mesh = trimesh.Trimesh(vertices, faces, process=False)
        mesh.export(directory / f"frame_{k}{suffix}")
    return directory


# --------------------------------------------------------------------------------------------
# Sliding window
# --------------------------------------------------------------------------------------------


def offset_model(driving: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Copies the driver and adds its position o in the window: shows which windows a frame came from."""
    return driving + torch.arange(driving.shape[1], dtype=driving.dtype)[None, :, None, None]


@pytest.mark.parametrize("combine, frames, expected", [
    ("mean", 5, [0, 0.5, 1, 1.5, 2]),   # frame t averages offsets of every window covering it
    ("center", 5, [1, 1, 1, 1, 1]),     # frame t is the centre (offset 1) of its own window
    ("mean", 2, [0, 1]),                # shorter than T: padded at the end
    ("mean", 1, [0]),
])
def test_sliding_window_combination(combine, frames, expected):
    seq, _ = driving_sequence(frames)
    out = animate_sequence(offset_model, seq, seq[0], window=3, combine=combine, batch_size=2)
    assert out.shape == seq.shape
    shift = out - center_bbox(seq)
    np.testing.assert_allclose(shift[..., 0].mean(1), expected, atol=1e-5)


def test_window_counts_and_regression_plan():
    assert num_windows(30, 3) == 28
    assert num_windows(30, 3, combine="center") == 30
    assert num_windows(2, 3) == 1
    assert window_plan(30, 3, slice(1, 2)) == (1, 1, [1])  # regression head: always centred windows
    with pytest.raises(ValueError):
        window_plan(30, 3, slice(None), "median")


def test_regression_head_and_other_topology_predict_every_frame():
    torch.manual_seed(0)
    model = AniFormer(AniFormerConfig(**TINY_MODEL, head="regression")).eval()
    seq, _ = driving_sequence(7)
    target, _ = body(3)  # 642 vertices, driver 162
    out = animate_sequence(model, seq, target, window=3, outputs=model.config.output_frames(), batch_size=4)
    assert out.shape == (7, len(target), 3) and np.isfinite(out).all()


def test_model_output_is_centred_unless_trajectory():
    seq, _ = driving_sequence(6)
    plain = animate_sequence(lambda d, t: d, seq, seq[0], window=3)
    np.testing.assert_allclose((plain.min(1) + plain.max(1)) / 2, 0, atol=1e-6)
    moved = animate_sequence(lambda d, t: d, seq, seq[0], window=3, trajectory=True)
    centres = (seq.min(1) + seq.max(1)) / 2
    np.testing.assert_allclose((moved.min(1) + moved.max(1)) / 2, centres - centres[0], atol=1e-5)


def test_natural_order_directory_and_glob(tmp_path):
    for name in ("frame_10.obj", "frame_2.obj", "frame_1.obj", "notes.txt"):
        (tmp_path / name).write_text("x")
    assert [p.name for p in driving_files(tmp_path)] == ["frame_1.obj", "frame_2.obj", "frame_10.obj"]
    assert [p.name for p in driving_files(str(tmp_path / "frame_1*.obj"))] == ["frame_1.obj", "frame_10.obj"]
    assert natural_key("a2") < natural_key("a10")
    with pytest.raises(MeshError, match="no file matches"):
        driving_files(str(tmp_path / "nothing_*.obj"))


def test_load_driving_names_first_mismatching_frame(tmp_path):
    write_driver(tmp_path, 4)
    v, f = body(1)
    trimesh.Trimesh(v, f, process=False).export(tmp_path / "frame_2.obj")
    with pytest.raises(MeshError, match=r"frame_2\.obj: 42 vertices, but the first driving frame frame_0\.obj has 162"):
        load_driving(driving_files(tmp_path))


# --------------------------------------------------------------------------------------------
# GLB
# --------------------------------------------------------------------------------------------


def test_glb_round_trip_and_layout(tmp_path):
    seq, faces = driving_sequence(12)
    path = write_glb(tmp_path / "a.glb", seq, faces, fps=24)
    scene = trimesh.load(path)
    assert scene.metadata["frames"] == 12 and scene.metadata["fps"] == 24
    (mesh,) = scene.geometry.values()
    np.testing.assert_allclose(mesh.vertices, seq[0], atol=1e-6)  # base = first frame
    back = read_glb(path)
    np.testing.assert_allclose(back["frames"], seq, atol=1e-6)
    np.testing.assert_array_equal(back["faces"], faces)
    np.testing.assert_allclose(back["times"], np.arange(12) / 24, atol=1e-7)
    gltf = back["gltf"]
    primitive = gltf["meshes"][0]["primitives"][0]
    assert len(primitive["targets"]) == 12 and len(gltf["meshes"][0]["weights"]) == 12
    sampler = gltf["animations"][0]["samplers"][0]
    assert sampler["interpolation"] == "STEP"
    assert gltf["animations"][0]["channels"][0]["target"] == {"node": 0, "path": "weights"}
    for accessor in [primitive["attributes"]["POSITION"]] + [t["POSITION"] for t in primitive["targets"]]:
        assert "min" in gltf["accessors"][accessor] and "max" in gltf["accessors"][accessor]  # required by glTF
    assert path.stat().st_size % 4 == 0


def test_write_obj_is_read_back(tmp_path):
    v, f = body(1)
    loaded = trimesh.load(write_obj(tmp_path / "x.obj", v, f), process=False)
    np.testing.assert_allclose(loaded.vertices, v, atol=1e-6)
    np.testing.assert_array_equal(loaded.faces, f)


# --------------------------------------------------------------------------------------------
# jobs/animate.py
# --------------------------------------------------------------------------------------------


def animate_main(argv):
    from jobs.animate import main

    return main([str(a) for a in argv])


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> dict:
    root = tmp_path_factory.mktemp("animate")
    target_v, target_f = body(3)  # another topology than the driver (642 vs 162 vertices)
    trimesh.Trimesh(target_v, target_f, process=False).export(root / "target.ply")
    return {"root": root, "checkpoint": make_checkpoint(root / "best.pt"), "driving": write_driver(root / "driving"),
            "target": root / "target.ply"}


@pytest.mark.slow
def test_animate_job_end_to_end(inputs, tmp_path, capsys):
    out = tmp_path / "anim"
    animate_main(["--checkpoint", inputs["checkpoint"], "--target", inputs["target"], "--driving", inputs["driving"],
                  "--out", out, "--fps", 25, "--no-progress", "--batch-size", 14])
    printed = capsys.readouterr().out
    assert str(out / "animation.glb") in printed and "30 frames" in printed
    objs = sorted((out / "frames").glob("*.obj"))
    assert len(objs) == 30 and objs[0].name == "frame_0000.obj"
    first = trimesh.load(objs[0], process=False)
    assert len(first.vertices) == 642
    scene = trimesh.load(out / "animation.glb")
    assert scene.metadata["frames"] == 30
    back = read_glb(out / "animation.glb")
    assert back["frames"].shape == (30, 642, 3)
    np.testing.assert_allclose(back["frames"][7], trimesh.load(objs[7], process=False).vertices, atol=1e-5)
    from PIL import Image

    with Image.open(out / "preview.gif") as gif:
        assert gif.n_frames == 30 and gif.size[0] == 2 * gif.size[1]  # driver | result
    summary = json.loads((out / "animation.json").read_text())
    assert summary["frames"] == 30 and summary["windows"] == 28 and summary["combine"] == "mean"
    assert [p.name for p in tmp_path.iterdir()] == ["anim"]  # no staging directory left behind


def test_animate_job_quads_are_triangulated(inputs, tmp_path):
    quad = tmp_path / "quad.obj"  # a 2x1 grid of quads
    quad.write_text("v 0 0 0\nv 0.5 0 0\nv 1 0 0\nv 0 0 1\nv 0.5 0 1\nv 1 0 1\nf 1 2 5 4\nf 2 3 6 5\n")
    animate_main(["--checkpoint", inputs["checkpoint"], "--target", quad, "--driving",
                  str(inputs["driving"] / "frame_[0-4].obj"), "--out", tmp_path / "o", "--no-progress",
                  "--preview-frames", 0])
    assert len(list((tmp_path / "o" / "frames").iterdir())) == 5
    assert read_glb(tmp_path / "o" / "animation.glb")["faces"].shape == (4, 3)


def _bad(kind: str, root: Path, inputs: dict) -> tuple[list, str]:
    """Arguments for one bad-input case and a word its error line must contain."""
    ckpt, target, driving = inputs["checkpoint"], inputs["target"], inputs["driving"]
    drv = root / "drv"

    def driver_with(name: str, text: str | bytes) -> Path:
        write_driver(drv, 3)
        path = drv / name
        path.write_bytes(text if isinstance(text, bytes) else text.encode())
        return drv

    args = {"checkpoint": ckpt, "target": target, "driving": driving}
    word = ""
    if kind == "missing target":
        args["target"], word = root / "nope.obj", "no such file"
    elif kind == "missing driving":
        args["driving"], word = root / "nope", "no file matches"
    elif kind == "empty driving dir":
        (root / "empty").mkdir()
        args["driving"], word = root / "empty", "no mesh files"
    elif kind == "garbage bytes":
        args["driving"], word = driver_with("frame_1.ply", os.urandom(300)), "cannot read"
    elif kind == "garbage obj":
        args["target"], word = root / "g.obj", "empty"
        (root / "g.obj").write_bytes(b"\x00\xff" * 50)
    elif kind == "unsupported format":
        (root / "t.txt").write_text("v 0 0 0")
        args["target"], word = root / "t.txt", "unsupported"
    elif kind == "empty file":
        args["driving"], word = driver_with("frame_1.obj", b""), "empty"
    elif kind == "no vertices":
        args["driving"], word = driver_with("frame_1.obj", "# only a comment\n"), "empty"
    elif kind == "nan":
        args["driving"], word = driver_with("frame_1.obj", "v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n"), "NaN"
    elif kind == "inf target":
        (root / "t.obj").write_text("v 0 0 0\nv inf 0 0\nv 0 1 0\nf 1 2 3\n")
        args["target"], word = root / "t.obj", "infinity"
    elif kind == "face out of range":
        (root / "t.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n")
        args["target"], word = root / "t.obj", "t.obj"
    elif kind == "face out of range ply":
        mesh = trimesh.Trimesh(*body(1), process=False)
        data = mesh.export(file_type="ply", encoding="ascii").replace(b"3 0 ", b"3 999 ", 1)
        (root / "t.ply").write_bytes(data)
        args["target"], word = root / "t.ply", "out of range"
    elif kind == "mixed vertex counts":
        write_driver(drv, 3)
        trimesh.Trimesh(*body(1), process=False).export(drv / "frame_2.obj")
        args["driving"], word = drv, "frame_2.obj: 42 vertices"
    elif kind == "over size limit":
        return [*_argv(args, root), "--max-vertices", "500"], "exceeds the limit of 500"
    elif kind == "too many frames":
        return [*_argv(args, root), "--max-frames", "10"], "exceeds --max-frames"
    elif kind == "garbage checkpoint":
        (root / "bad.pt").write_bytes(os.urandom(200))
        args["checkpoint"], word = root / "bad.pt", "not a readable checkpoint"
    elif kind == "checkpoint config mismatch":
        state = torch.load(ckpt, weights_only=True)
        state["config"]["model"]["channels"] = [32]
        torch.save(state, root / "mismatch.pt")
        args["checkpoint"], word = root / "mismatch.pt", "does not match its model config"
    elif kind == "missing checkpoint":
        args["checkpoint"], word = root / "none.pt", "checkpoint not found"
    elif kind == "bad argument":
        return [*_argv(args, root), "--batch-size", "0"], "--batch-size must be >= 1"
    elif kind == "unknown option":
        return [*_argv(args, root), "--frobnicate"], "unrecognized arguments"
    elif kind == "out not empty":
        (root / "out").mkdir()
        (root / "out" / "keep.txt").write_text("precious")
        return _argv(args, root), "not empty"
    return _argv(args, root), word


def _argv(args: dict, root: Path) -> list:
    return ["--checkpoint", args["checkpoint"], "--target", args["target"], "--driving", args["driving"],
            "--out", root / "out", "--no-progress"]


BAD_CASES = ["missing target", "missing driving", "empty driving dir", "garbage bytes", "garbage obj",
             "unsupported format", "empty file", "no vertices", "nan", "inf target", "face out of range",
             "face out of range ply", "mixed vertex counts", "over size limit", "too many frames", "garbage checkpoint",
             "checkpoint config mismatch", "missing checkpoint", "bad argument", "unknown option", "out not empty"]


@pytest.mark.parametrize("kind", BAD_CASES)
def test_animate_bad_input_is_one_line_and_leaves_nothing(kind, inputs, tmp_path, capsys):
    argv, word = _bad(kind, tmp_path, inputs)
    before = set(tmp_path.iterdir())
    with pytest.raises(SystemExit) as exc:
        run(animate_main, [str(a) for a in argv])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and word in lines[0], err
    assert "Traceback" not in err
    assert set(tmp_path.iterdir()) == before  # no output dir, no staging dir
    if kind == "out not empty":
        assert [p.name for p in (tmp_path / "out").iterdir()] == ["keep.txt"]


def test_animate_unreadable_file(inputs, tmp_path, capsys):
    if os.geteuid() == 0:
        pytest.skip("root reads files regardless of permissions")
    target = tmp_path / "t.ply"
    target.write_bytes(Path(inputs["target"]).read_bytes())
    target.chmod(0)
    with pytest.raises(UserError, match="cannot read"):
        animate_main(_argv({**inputs, "target": target}, tmp_path))


def test_animate_refuses_nonempty_out_then_overwrites(inputs, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "old.txt").write_text("old")
    argv = _argv({**inputs, "driving": str(inputs["driving"] / "frame_[0-2].obj")}, tmp_path) + ["--preview-frames", "0"]
    with pytest.raises(UserError, match="not empty"):
        animate_main(argv)
    animate_main(argv + ["--overwrite"])
    assert sorted(p.name for p in out.iterdir()) == ["animation.glb", "animation.json", "frames"]


def test_animate_script_exit_code_and_one_line(inputs, tmp_path):
    """As a real process: exit 2, one line on stderr, no traceback."""
    bad = tmp_path / "bad.obj"
    bad.write_text("v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n")
    argv = [sys.executable, str(ROOT / "jobs" / "animate.py"), *map(str, _argv({**inputs, "target": bad}, tmp_path))]
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0 and "NaN" in proc.stderr, proc.stderr
    assert not (tmp_path / "out").exists()
