"""Blender imports our GLBs upright, at their frame rate, in the air mid-jump (bench/blender_import.py).

Runs Debian's Blender (3.4.1, ``apt-get install blender python3-numpy``, which .ci/run does) headless
on GLBs of the tests' ellipsoid and of jobs/animate.py with the tiny checkpoint; skipped where
``blender`` is not on PATH. The script evaluates the imported mesh in Blender's world space (shape
keys, chunk visibility, root motion) and exits 1 on a failed check: a y-up mix-up, the wrong frame
rate and a file whose body does not match the job's OBJ frames each fail it (tested below).
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest
from test_animate import animate_main, body_pixels, jump_and_walk, make_checkpoint, world_frames, write_driver

import aniformer.io.glb
from aniformer.io.glb import write_glb
from aniformer.io.mesh import load_mesh, write_obj

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "bench" / "blender_import.py"
BLENDER = shutil.which("blender")
pytestmark = pytest.mark.skipif(BLENDER is None, reason="no blender on PATH (.ci/run installs Debian's blender)")


def blender_import(glb: Path, *args) -> tuple[int, dict | None, str]:
    """Run the script on ``glb``: (exit status, its report, its output)."""
    report = glb.with_suffix(".json")
    proc = subprocess.run([BLENDER, "-b", "--factory-startup", "--python-exit-code", "1", "--python", str(SCRIPT),
                           "--", str(glb), "--json", str(report), *map(str, args)],
                          capture_output=True, text=True, timeout=300)
    output = proc.stdout + proc.stderr
    return proc.returncode, (json.loads(report.read_text()) if report.exists() else None), output


def jump_glb(path: Path, frames: int = 30, **kw) -> Path:
    """The three.js test's clip: a 1.7 m ellipsoid walking 1 m along x and jumping 0.4 m mid-clip."""
    seq, faces = jump_and_walk(frames)
    local, move = world_frames(seq, seq[0], faces)
    return write_glb(path, local, faces, fps=30, name="jump", translation=move, **kw)


def test_blender_imports_a_jump_upright_in_the_air_at_its_fps(tmp_path):
    glb = jump_glb(tmp_path / "jump.glb")
    png = tmp_path / "jump.png"
    code, report, output = blender_import(glb, "--height", 1.7, "--airborne", 0.35, "--png", png,
                                          "--resolution", 160, 200, "--samples", 4)
    assert code == 0, output[-3000:]
    assert report["blender_default_fps"] == 24 and report["fps"] == 30  # set from the file before importing
    assert report["action_frame_ranges"] == [[0.0, 30.0]] and report["frame_range"] == [0, 29]
    assert report["seconds"] == pytest.approx(1.0) and report["scene_custom_properties"]["fps"] == 30
    first, mid = report["frame_0"], report["frame_15"]
    assert first["z_extent"] == pytest.approx(1.7, abs=1e-3)  # Blender is z up: it stands up
    assert first["lowest_z"] == pytest.approx(0, abs=1e-3) and mid["lowest_z"] > 0.35  # off the floor mid-jump
    assert mid["centre"][0] - first["centre"][0] == pytest.approx(15 / 29, abs=1e-3)  # and it walked along x
    assert report["visible_chunks"] == [1, 1] and report["failures"] == []
    assert body_pixels(png) > 1000, "the body is not in the picture"  # ~2,800 of 32,000; the background 0


def test_blender_flags_a_z_up_glb_as_lying_down(tmp_path, monkeypatch):
    monkeypatch.setattr(aniformer.io.glb, "to_gltf_axes", lambda v: v)  # the old bug: z-up positions in glTF
    code, report, output = blender_import(jump_glb(tmp_path / "down.glb"), "--height", 1.7)
    assert code == 1 and "does not stand up" in output, output[-3000:]
    assert report["frame_0"]["z_extent"] < 0.5  # the 0.24 m depth of the body: it lies face down


def test_blender_at_its_default_24_fps_skips_frames(tmp_path):
    code, report, output = blender_import(jump_glb(tmp_path / "jump.glb"), "--fps", 24, "--height", 1.7)
    assert code == 1 and report["action_frame_ranges"] == [[0.0, 24.0]], output[-3000:]  # 30 frames in 24


def test_blender_plays_chunks_of_a_longer_clip_one_at_a_time(tmp_path):
    code, report, output = blender_import(jump_glb(tmp_path / "long.glb", 40, frames_per_mesh=16), "--frame", 20,
                                          "--height", 1.7, "--airborne", 0.35)
    assert code == 0 and report["visible_chunks"] == [1, 1], output[-3000:]
    assert len([o for o in report["objects"] if o.endswith("(MESH)")]) == 3  # frames 0-15, 16-31, 32-39


@pytest.mark.slow
def test_blender_imports_the_animate_jobs_glb_where_its_obj_frames_are(tmp_path):
    out = tmp_path / "anim"
    animate_main(["--checkpoint", make_checkpoint(tmp_path / "best.pt"), "--target", write_driver(tmp_path / "drv") /
                  "frame_0.obj", "--driving", tmp_path / "drv", "--out", out, "--no-progress", "--preview-frames", 0,
                  "--force"])  # untrained: the self-check refuses its result
    code, report, output = blender_import(out / "animation.glb", "--objs", out / "frames", "--frame", 7)
    assert code == 0, output[-3000:]  # frame 7: the driver's hop and sideways bend at their highest
    assert report["max_deviation_from_obj_frame_0_m"] < 1e-4 and report["max_deviation_from_obj_frame_7_m"] < 1e-4
    assert report["fps"] == 30 and report["frame_range"] == [0, 29]
    # The OBJs are what the job wrote: a vertex moved in the GLB only is caught.
    obj = out / "frames" / "frame_0007.obj"
    vertices, faces = load_mesh(obj)
    vertices[0, 0] += 0.01
    write_obj(obj, vertices, faces)
    code, _, output = blender_import(out / "animation.glb", "--objs", out / "frames", "--frame", 7)
    assert code == 1 and "frame 7: a vertex is 0.0100 m from" in output, output[-3000:]
