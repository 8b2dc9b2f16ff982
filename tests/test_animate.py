"""Sliding-window animation, the GLB writer, jobs/animate.py end to end and its bad-input handling.

Real clients: every GLB a test here writes goes through the Khronos glTF validator (npm
``gltf-validator``), and the world-space and long clips are played in three.js in headless
Chromium (tests/js/player.html). Both come from tests/js/package-lock.json (``npm ci --prefix
tests/js``, which .ci/run does); without node or Chromium those checks are skipped.
"""

from __future__ import annotations

import contextlib
import functools
import html
import http.server
import json
import os
import re
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
import yaml

from aniformer.animate import (
    animate_sequence,
    body_scale,
    driving_files,
    driving_fps,
    load_driving,
    num_windows,
    root_motion,
    window_plan,
)
from aniformer.checkpoint import save_checkpoint
from aniformer.cli.exits import run
from aniformer.errors import MeshError, UserError
from aniformer.geometry import center_bbox
from aniformer.io.files import natural_key
from aniformer.io.glb import MAX_MORPH_TARGETS, mesh_chunks, read_document, read_glb, to_gltf_axes, write_glb
from aniformer.io.mesh import write_obj
from aniformer.model import AniFormer, AniFormerConfig

ROOT = Path(__file__).resolve().parents[1]
TINY_MODEL = dict(channels=(16,), extractor_channels=(8, 16), heads=2, window=3)
JS = ROOT / "tests" / "js"
NODE = shutil.which("node")
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
VALIDATOR_READY = NODE is not None and (JS / "node_modules" / "gltf-validator").is_dir()
THREE_READY = CHROMIUM is not None and (JS / "node_modules" / "three").is_dir()
NEEDS_VALIDATOR = pytest.mark.skipif(not VALIDATOR_READY, reason="no node or gltf-validator: npm ci --prefix tests/js")
NEEDS_THREE = pytest.mark.skipif(not THREE_READY, reason="no chromium or three: .ci/run installs both")


def khronos_reports(paths: list[Path]) -> list[dict]:
    """The Khronos validator's counts and messages for each GLB (tests/js/validate.mjs)."""
    proc = subprocess.run([NODE, str(JS / "validate.mjs"), *map(str, paths)], capture_output=True, text=True,
                          timeout=600, check=True)
    return [json.loads(line) for line in proc.stdout.splitlines()]


@pytest.fixture(autouse=True)
def every_glb_passes_the_khronos_validator(tmp_path):
    yield
    written = sorted(tmp_path.rglob("*.glb"))
    if written and VALIDATOR_READY:
        for report in khronos_reports(written):
            assert report["numErrors"] == 0 and report["numWarnings"] == 0, report


class QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):  # keep pytest's output to the test's own
        pass


def play_in_threejs(glb: Path, frame: int, fps: float, www: Path) -> tuple[dict, Path]:
    """Load ``glb`` in three.js in headless Chromium, play it to ``frame``: (what the page saw, screenshot)."""
    www.mkdir()
    (www / "node_modules").symlink_to(JS / "node_modules", target_is_directory=True)
    shutil.copy(JS / "player.html", www)
    shutil.copy(glb, www / "clip.glb")
    handler = functools.partial(QuietHandler, directory=str(www))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    shot = www / "screenshot.png"
    cmd = [CHROMIUM, "--headless", "--disable-gpu", "--enable-unsafe-swiftshader", "--use-angle=swiftshader",
           "--no-first-run", "--disable-background-networking", "--disable-component-update", "--disable-sync",
           f"--user-data-dir={www / 'profile'}", "--window-size=900,700", "--hide-scrollbars",
           "--virtual-time-budget=60000", f"--screenshot={shot}", "--dump-dom",
           f"http://127.0.0.1:{server.server_address[1]}/player.html?glb=clip.glb&frame={frame}&fps={fps}"]
    if os.geteuid() == 0:
        cmd.insert(2, "--no-sandbox")  # Chromium's sandbox refuses to run as root
    try:
        page = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    finally:
        server.shutdown()
        server.server_close()
    found = re.search(r'<pre id="result">(.*?)</pre>', page.stdout, re.S)
    assert found, page.stdout[-2000:] + page.stderr[-2000:]
    result = json.loads(html.unescape(found.group(1)))
    assert result["ok"] and result["glErrors"] == 0, result  # a morph texture too large is GL_INVALID_VALUE
    keep = os.environ.get("ANIFORMER_KEEP_SCREENSHOTS")  # a folder to keep the screenshots in (docs)
    if keep:
        shutil.copyfile(shot, Path(keep) / f"threejs_{glb.stem}_frame{frame}.png")
    return result, shot


def body_pixels(shot: Path) -> int:
    """Pixels of the body's blue (the grid and the background are grey or white)."""
    from PIL import Image  # matplotlib's dependency

    with Image.open(shot) as im:
        rgb = np.asarray(im.convert("RGB")).astype(int)
    return int(((rgb[..., 2] - rgb[..., 0]) > 25).sum())


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


def jump_and_walk(frames: int = 30) -> tuple[np.ndarray, np.ndarray]:
    """The ellipsoid standing on a floor at z = 0.5, walking 1 m along +x and jumping 0.4 m mid-clip."""
    v, f = body(2)
    t = np.arange(frames)[:, None] / max(frames - 1, 1)
    seq = np.repeat(v[None], frames, 0) + [0.3, -0.2, 0.5 + 0.85]
    seq[..., 0] += 1.0 * t
    seq[..., 2] += 0.4 * np.clip(np.sin(np.pi * (t - 0.25) / 0.5), 0, None) * (np.abs(t - 0.5) < 0.25)
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


def still_target_model(driving: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Outputs the (centred) target in every frame: the placement alone moves it."""
    return target[:, None].expand(-1, driving.shape[1], -1, -1)


def world_frames(seq: np.ndarray, target: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What jobs/animate.py writes for ``still_target_model``: (local frames, root translation)."""
    local = center_bbox(animate_sequence(still_target_model, seq, target, window=3))
    return local, root_motion(seq, local, body_scale(target, faces, seq[0], faces))


def test_model_output_is_centred_and_root_motion_places_it_where_the_driver_is():
    seq, faces = jump_and_walk(30)
    plain = animate_sequence(lambda d, t: d, seq, seq[0], window=3)
    np.testing.assert_allclose((plain.min(1) + plain.max(1)) / 2, 0, atol=1e-6)  # the model sees centred meshes
    local, move = world_frames(seq, seq[0], faces)
    world = local + move[:, None]
    centres = (seq.min(1) + seq.max(1)) / 2
    np.testing.assert_allclose(((world.min(1) + world.max(1)) / 2)[:, :2], centres[:, :2], atol=1e-5)  # same place
    np.testing.assert_allclose(world[..., 2].min(1), seq[..., 2].min(1) - 0.5, atol=1e-5)  # the floor goes to z = 0
    half, half_move = world_frames(seq, seq[0] * 0.5, faces)  # a half-size target: half the steps, half the jump
    half_world = half + half_move[:, None]
    np.testing.assert_allclose(half_move[:, 0] - half_move[0, 0], 0.5 * (centres[:, 0] - centres[0, 0]), atol=1e-5)
    np.testing.assert_allclose(half_world[..., 2].min(1), 0.5 * (seq[..., 2].min(1) - 0.5), atol=1e-5)


def test_natural_order_directory_and_glob(tmp_path):
    for name in ("frame_10.obj", "frame_2.obj", "frame_1.obj", "notes.txt"):
        (tmp_path / name).write_text("x")
    assert [p.name for p in driving_files(tmp_path)] == ["frame_1.obj", "frame_2.obj", "frame_10.obj"]
    assert [p.name for p in driving_files(str(tmp_path / "frame_1*.obj"))] == ["frame_1.obj", "frame_10.obj"]
    assert natural_key("a2") < natural_key("a10")
    with pytest.raises(MeshError, match="no file matches"):
        driving_files(str(tmp_path / "nothing_*.obj"))


def test_driving_frames_must_share_the_first_frames_faces(tmp_path):
    write_driver(tmp_path, 4)
    v, f = body(2)
    trimesh.Trimesh(v, f[:, ::-1], process=False).export(tmp_path / "frame_3.obj")  # same vertices, flipped faces
    with pytest.raises(MeshError, match=r"frame_3\.obj: other faces than the first driving frame frame_0\.obj"):
        load_driving(driving_files(tmp_path))


def test_driving_fps_from_a_sidecar(tmp_path):
    write_driver(tmp_path, 2)
    files = driving_files(tmp_path)
    assert driving_fps(files) is None
    (tmp_path / "export.json").write_text('{"frames": 2}')
    assert driving_fps(files) is None
    (tmp_path / "sequence.json").write_text('{"fps": 60}')
    assert driving_fps(files) == 60.0
    (tmp_path / "sequence.json").write_text('{"fps": -1}')
    with pytest.raises(MeshError, match="fps must be a positive number"):
        driving_fps(files)


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
    move = np.stack([np.arange(12) * 0.1, np.zeros(12), np.full(12, 0.85)], 1).astype(np.float32)
    path = write_glb(tmp_path / "a.glb", seq, faces, fps=24, name="me_jump", translation=move)
    scene = trimesh.load(path)
    assert scene.metadata["frames"] == 12 and scene.metadata["fps"] == 24
    (mesh,) = scene.geometry.values()
    np.testing.assert_allclose(mesh.vertices, to_gltf_axes(seq[0]), atol=1e-6)  # base = first frame, y up
    back = read_glb(path)
    np.testing.assert_allclose(back["frames"], seq + move[:, None], atol=1e-5)
    np.testing.assert_allclose(back["local"], seq, atol=1e-5)
    np.testing.assert_array_equal(back["faces"], faces)
    assert back["duration"] == pytest.approx(12 / 24)  # every frame is shown for 1 / fps, the last one too
    gltf = back["gltf"]
    assert [n["name"] for n in gltf["nodes"]] == ["me_jump", "me_jump"] and gltf["meshes"][0]["name"] == "me_jump"
    assert gltf["animations"][0]["name"] == "me_jump" and gltf["nodes"][0]["translation"] == pytest.approx([0, 0.85, 0])
    primitive = gltf["meshes"][0]["primitives"][0]
    assert len(primitive["targets"]) == 11 and len(gltf["meshes"][0]["weights"]) == 11  # frame 0 is the base
    assert gltf["meshes"][0]["extras"]["targetNames"][0] == "frame_1"  # Blender's shape key names
    samplers = gltf["animations"][0]["samplers"]
    assert {s["interpolation"] for s in samplers} == {"STEP"}
    assert {c["target"]["path"] for c in gltf["animations"][0]["channels"]} == {"weights", "translation"}
    weights = gltf["accessors"][samplers[0]["output"]]
    assert "sparse" in weights and weights["sparse"]["count"] == 12 and "bufferView" not in weights  # linear in N
    assert path.stat().st_size % 4 == 0
    _, accessor = read_document(path)
    for k in (1, 11):  # each target is its frame minus the base in glTF's axes, bit for bit (a still vertex's +0)
        expected = to_gltf_axes(seq[k]) - to_gltf_axes(seq[0])
        assert (expected == 0).any() and np.array_equal(accessor(primitive["targets"][k - 1]["POSITION"]).view(np.uint32),
                                                        expected.view(np.uint32))


def test_glb_chunks_a_long_clip_into_meshes_of_at_most_frames_per_mesh(tmp_path):
    seq, faces = driving_sequence(21)
    back = read_glb(write_glb(tmp_path / "c.glb", seq, faces, fps=10, name="c", frames_per_mesh=8))
    assert mesh_chunks(21, 8) == [(0, 8), (8, 16), (16, 21)]
    gltf = back["gltf"]
    assert [n["name"] for n in gltf["nodes"]] == ["c", "c_00", "c_08", "c_16"]
    assert [len(m["primitives"][0]["targets"]) for m in gltf["meshes"]] == [7, 7, 4]
    assert [n.get("scale") for n in gltf["nodes"][1:]] == [None, [0, 0, 0], [0, 0, 0]]  # frame 0 shows chunk 0
    np.testing.assert_allclose(back["frames"], seq, atol=1e-5)
    assert back["duration"] == pytest.approx(2.1)


def test_glb_of_one_frame_has_no_animation(tmp_path):
    seq, faces = driving_sequence(1)
    back = read_glb(write_glb(tmp_path / "one.glb", seq, faces, translation=np.zeros((1, 3), np.float32)))
    assert "animations" not in back["gltf"] and back["frames"].shape == seq.shape


@NEEDS_THREE
def test_threejs_plays_a_jump_upright_where_the_driver_is(tmp_path):
    seq, faces = jump_and_walk(30)
    local, move = world_frames(seq, seq[0], faces)
    glb = write_glb(tmp_path / "jump.glb", local, faces, fps=30, name="jump", translation=move)
    page, shot = play_in_threejs(glb, 15, 30, tmp_path / "www")
    assert page["duration"] == pytest.approx(1.0) and page["morphs"] == 29 and page["meshes"] == 1
    first, now = page["first"], page["now"]
    assert now["shown"] == first["shown"] == 1
    assert now["max"][1] - now["min"][1] == pytest.approx(1.7, abs=1e-3)  # y extent = body height: it stands up
    assert first["min"][1] == pytest.approx(0, abs=1e-4)  # feet on the floor at frame 0
    assert now["min"][1] > 0.35  # in the air mid-jump
    assert now["min"][0] - first["min"][0] == pytest.approx(15 / 29, abs=1e-3)  # and it walked along x
    assert body_pixels(shot) > 500  # drawn


@NEEDS_THREE
@pytest.mark.parametrize("frames_per_mesh", [256, MAX_MORPH_TARGETS])
def test_threejs_plays_a_clip_longer_than_its_morph_target_limit(tmp_path, frames_per_mesh):
    seq, faces = jump_and_walk(3000)
    local, move = world_frames(seq, seq[0], faces)
    glb = write_glb(tmp_path / "long.glb", local, faces, fps=30, name="long", translation=move,
                    frames_per_mesh=frames_per_mesh)
    page, shot = play_in_threejs(glb, 2600, 30, tmp_path / "www")
    chunks = len(mesh_chunks(3000, frames_per_mesh))
    assert page["duration"] == pytest.approx(100.0) and page["meshes"] == chunks and page["morphs"] == 3000 - chunks
    assert page["now"]["shown"] == 1 and page["now"]["min"][0] - page["first"]["min"][0] == pytest.approx(2600 / 2999, abs=1e-3)
    assert body_pixels(shot) > 500


def test_write_obj_is_read_back(tmp_path):
    v, f = body(1)
    loaded = trimesh.load(write_obj(tmp_path / "x.obj", v, f), process=False)
    np.testing.assert_allclose(loaded.vertices, v, atol=1e-6)
    np.testing.assert_array_equal(loaded.faces, f)


def test_write_obj_writes_plain_v_and_f_lines(tmp_path):
    vertices, faces = np.array([[0.5, -1.25, 2.0], [1e-7, 3.0, -0.0000004], [1, 2, 3]]), np.array([[0, 1, 2], [2, 1, 0]])
    for _ in range(2):  # the second write takes the faces' block from the cache
        text = write_obj(tmp_path / "t.obj", vertices, faces).read_text()
        assert text == ("# aniformer\nv 0.500000 -1.250000 2.000000\nv 0.000000 3.000000 -0.000000\n"
                        "v 1.000000 2.000000 3.000000\nf 1 2 3\nf 3 2 1\n")


def test_write_obj_numbers_match_printf_byte_for_byte(tmp_path):
    rng = np.random.default_rng(0)
    halves = (np.arange(-3000, 3000) + 0.5) * 1e-6  # decimal ties, which float64 holds only approximately
    finite = np.concatenate([rng.standard_normal(3000) * scale for scale in (1e-4, 1, 30, 1e4, 1e8)]
                            + [rng.standard_normal(3000).astype(np.float32), halves, np.arange(3000) * 1e-3,
                               [0.0, -0.0, 0.9999995, -9.9999999, 999999.9999996, 4.5e9]])
    for vertices in (finite.reshape(-1, 3), np.array([[1.5, np.nan, -np.inf]])):  # printf itself formats non-finite
        text = write_obj(tmp_path / "t.obj", vertices, np.array([[0, 0, 0]])).read_bytes()
        expected = "".join(f"v {x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in vertices.tolist())
        assert text == b"# aniformer\n" + expected.encode() + b"f 1 1 1\n"


@pytest.mark.parametrize("block_raises", [False, True])
def test_objs_written_by_a_process_are_the_ones_written_here(tmp_path, block_raises):
    from tqdm import tqdm

    from aniformer.animation_outputs import objs_written_beside

    vertices, faces = body(2)
    frames = vertices[None] + np.linspace(0, 0.3, 12)[:, None, None] * np.array([1.0, -0.5, 0.2])
    here, beside = tmp_path / "here", tmp_path / "staged"
    here.mkdir(), beside.mkdir()
    with tqdm(total=12, disable=True) as bar, objs_written_beside(here / "frames", frames, faces, False, {}, bar):
        pass
    seconds = {}
    with contextlib.suppress(RuntimeError), tqdm(total=12, disable=True) as bar, \
            objs_written_beside(beside / "frames", frames, faces, True, seconds, bar):
        assert (beside / ".frames.npy").is_file()  # the writer's input, beside the frames
        if block_raises:  # e.g. the GLB failed: the writer is ended, its input removed
            raise RuntimeError("the other outputs failed")
    assert [p.name for p in beside.iterdir()] == ["frames"]
    if not block_raises:
        assert sorted(p.name for p in (beside / "frames").iterdir()) == [f"frame_{k:04d}.obj" for k in range(12)]
        for k in (0, 11):
            assert (beside / "frames" / f"frame_{k:04d}.obj").read_bytes() == \
                (here / "frames" / f"frame_{k:04d}.obj").read_bytes()
        assert seconds["write OBJ"] >= 0


def test_preview_mesh_decimates_every_frame_alike():
    from aniformer.io.render import preview_mesh

    sphere = trimesh.creation.icosphere(subdivisions=4)  # 5,120 faces
    shift = np.array([0.1, -0.2, 0.3])
    frames = np.stack([sphere.vertices, sphere.vertices + shift, 2 * sphere.vertices])
    decimated, faces = preview_mesh(frames, np.asarray(sphere.faces), 500)
    assert len(faces) <= 500 and decimated.shape == (3, faces.max() + 1, 3)
    np.testing.assert_allclose(decimated[1], decimated[0] + shift, atol=1e-9)
    np.testing.assert_allclose(decimated[2], 2 * decimated[0], atol=1e-9)
    assert np.abs(np.linalg.norm(decimated[0], axis=1) - 1).max() < 0.01  # on the sphere


def test_preview_of_a_mesh_split_at_seams_stays_closed():
    """A closed sphere written with its vertices split at seams (8 islands) is decimated whole for the preview:
    no edge of the drawn mesh is open, as none of the sphere's is (split apart, each island's rim was decimated
    on its own and the preview showed the background through cracks)."""
    from aniformer.io.render import preview_mesh
    from aniformer.synth.variants import split_at_seams

    sphere = trimesh.creation.icosphere(subdivisions=4)
    centres = sphere.triangles_center
    islands = (centres[:, 0] > 0) * 4 + (centres[:, 1] > 0) * 2 + (centres[:, 2] > 0)
    vertices, faces, _ = split_at_seams(np.asarray(sphere.vertices), np.asarray(sphere.faces), islands)
    assert len(vertices) > len(sphere.vertices)
    decimated, drawn = preview_mesh(vertices[None], faces, 500)
    edges = np.sort(drawn[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, uses = np.unique(edges, axis=0, return_counts=True)
    assert len(drawn) <= 500 and (uses == 2).all()


def test_preview_rasterizer_draws_a_closed_surface_without_holes_and_the_nearest_face_in_front():
    """The previews' z-buffer: a sphere covers exactly its disc, whichever way its faces wind; of two
    overlapping squares the nearer one shows, whichever is listed first."""
    from aniformer.io.render import Camera, rasterize

    sphere = trimesh.creation.icosphere(subdivisions=3)  # 1,280 faces, a few pixels each at 64 pixels
    camera = Camera.looking_at(sphere.vertices[None], (10.0, -60.0), 64)
    radius = 64 / (2 * camera.half)  # the unit sphere's radius in pixels
    centre, _ = camera.project(np.zeros(3))
    rows, columns = np.mgrid[:64, :64]
    distance = np.hypot(columns + 0.5 - centre[0], rows + 0.5 - centre[1])
    for faces in (sphere.faces, sphere.faces[:, ::-1]):
        index = rasterize(np.asarray(sphere.vertices)[faces], camera)
        assert (index[distance < 0.97 * radius] >= 0).all() and (index[distance > radius + 1] == -1).all()
        assert index.max() < len(faces)
    triangles = np.asarray(sphere.vertices)[sphere.faces]
    whole = rasterize(triangles, camera)
    assert np.array_equal(rasterize(triangles, camera, pairs_at_once=500), whole)  # in chunks: the same picture
    torn, shown = triangles.copy(), whole[32, 32]
    torn[shown, 0] = np.nan  # a face not finite is not drawn (the one behind shows); the others as before
    missing = rasterize(torn, camera)
    assert shown >= 0 and missing[32, 32] >= 0 and (missing != shown).all()
    assert np.array_equal(missing[whole != shown], whole[whole != shown])
    right, up, towards = camera.axes
    square = np.array([[-1, -1], [1, -1], [1, 1], [-1, -1], [1, 1], [-1, 1]], float) * 0.5
    flat = (square[:, :1] * right + square[:, 1:] * up).reshape(2, 3, 3)
    near, far = flat + 0.3 * towards, flat - 0.3 * towards + 0.2 * right
    middle = tuple(np.floor(camera.project(np.zeros(3))[0]).astype(int)[::-1])
    assert rasterize(np.concatenate([near, far]), camera)[middle] in (0, 1)
    assert rasterize(np.concatenate([far, near]), camera)[middle] in (2, 3)


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
def test_animate_job_end_to_end(inputs, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("aniformer.animation_outputs.OBJ_PROCESS_VERTEX_FRAMES", 1)  # a clip as big as a studio's
    out = tmp_path / "anim"
    animate_main(["--checkpoint", inputs["checkpoint"], "--target", inputs["target"], "--driving", inputs["driving"],
                  "--out", out, "--fps", 25, "--no-progress", "--batch-size", 14, "--force"])  # untrained: it tears
    printed = capsys.readouterr().out
    assert f"{out / 'animation.glb'} (30 frames at 25 fps, 1.20 s)" in printed and "30 frames" in printed
    objs = sorted((out / "frames").glob("*.obj"))
    assert len(objs) == 30 and objs[0].name == "frame_0000.obj"
    first = trimesh.load(objs[0], process=False)
    assert len(first.vertices) == 642
    scene = trimesh.load(out / "animation.glb")
    assert scene.metadata["frames"] == 30
    back = read_glb(out / "animation.glb")
    assert back["frames"].shape == (30, 642, 3) and back["duration"] == pytest.approx(30 / 25)
    assert back["gltf"]["animations"][0]["name"] == "target_driving"  # --target target.ply, --driving driving/
    np.testing.assert_allclose(back["frames"][7], trimesh.load(objs[7], process=False).vertices, atol=1e-5)
    driving, _ = load_driving(driving_files(inputs["driving"]))
    assert back["frames"][..., 2].min() == pytest.approx(0, abs=1e-5)  # on the floor (the driver's lowest point)
    hop = back["frames"][..., 2].min(1)
    assert hop.argmax() == (driving[..., 2].min(1)).argmax() and hop.max() > 0.05  # leaves it when the driver does
    from PIL import Image

    with Image.open(out / "preview.gif") as gif:
        assert gif.n_frames == 30 and gif.size[0] == 2 * gif.size[1]  # driver | result
    summary = json.loads((out / "animation.json").read_text())
    assert summary["frames"] == 30 and summary["windows"] == 28 and summary["combine"] == "mean"
    assert summary["fps"] == 25 and summary["name"] == "target_driving" and not summary["output_centred"]
    assert [p.name for p in tmp_path.iterdir()] == ["anim"]  # no staging directory left behind


@pytest.mark.parametrize("unit", ["cm", "auto"])
def test_animate_job_centred_named_in_centimetres_at_the_drivers_fps(inputs, tmp_path, unit):
    """Inputs authored in centimetres, said (``--unit cm``) or told by their size (``auto``, the default)."""
    drv = tmp_path / "clip"
    seq, faces = driving_sequence(4)
    for k, vertices in enumerate(seq * 100):  # authored in centimetres
        write_obj(drv / f"f{k}.obj", vertices, faces)
    (drv / "sequence.json").write_text('{"fps": 50}')
    target = write_obj(tmp_path / "t.obj", body(3)[0] * 100, body(3)[1])
    out = tmp_path / "o"
    animate_main(["--checkpoint", inputs["checkpoint"], "--target", target, "--driving", drv, "--out", out,
                  "--unit", unit, "--center", "--name", "hero", "--no-progress", "--preview-frames", 0, "--force"])
    summary = json.loads((out / "animation.json").read_text())
    assert summary["unit"] == "cm" and {role: u["unit"] for role, u in summary["units"].items()} == {
        "target": "cm", "driver": "cm"}
    back = read_glb(out / "animation.glb")
    assert back["duration"] == pytest.approx(4 / 50) and back["gltf"]["nodes"][0]["name"] == "hero"
    assert "translation" not in back["gltf"]["nodes"][0]
    np.testing.assert_allclose((back["frames"].min(1) + back["frames"].max(1)) / 2, 0, atol=1e-5)  # centred
    obj = trimesh.load(out / "frames" / "frame_0001.obj", process=False).vertices  # OBJs in the inputs' unit
    np.testing.assert_allclose(obj / 100, back["frames"][1], atol=1e-5)


@pytest.mark.slow
@NEEDS_THREE
def test_animate_job_glb_plays_in_threejs(inputs, tmp_path):
    out = tmp_path / "anim"
    animate_main(["--checkpoint", inputs["checkpoint"], "--target", inputs["target"], "--driving", inputs["driving"],
                  "--out", out, "--no-progress", "--preview-frames", 0, "--force"])  # untrained: it tears
    page, shot = play_in_threejs(out / "animation.glb", 15, 30, tmp_path / "www")
    assert page["duration"] == pytest.approx(1.0) and page["morphs"] == 29 and page["now"]["shown"] == 1
    assert body_pixels(shot) > 500


def test_animate_job_plays_an_animated_glb_as_the_folder_of_its_frames(inputs, tmp_path):
    """``--driving clip.glb``: the file's animation, frame for frame, at its rate (before: its rest pose alone,
    one frame, exit 0)."""
    driving, faces = load_driving(driving_files(inputs["driving"]))
    clip = write_glb(tmp_path / "clip.glb", driving, faces, fps=25, frames_per_mesh=8)
    outs = {}
    for name, source, rate in (("folder", inputs["driving"], ["--fps", 25]), ("glb", clip, [])):  # the GLB says 25
        outs[name] = tmp_path / name
        animate_main(["--checkpoint", inputs["checkpoint"], "--target", inputs["target"], "--driving", source,
                      "--out", outs[name], "--no-progress", "--preview-frames", 0, "--force", *rate])
    summary = json.loads((outs["glb"] / "animation.json").read_text())
    assert summary["frames"] == 30 and summary["fps"] == 25 and summary["name"] == "target_clip"
    assert summary["driving_animation"] == {"name": "aniformer", "index": 0, "of": 1, "fps": 25.0, "frames": 30}
    assert summary["up"]["driver"] == {"axis": "y", "why": "glTF is y-up"}
    for k in (0, 13, 29):
        np.testing.assert_allclose(trimesh.load(outs["glb"] / "frames" / f"frame_{k:04d}.obj", process=False).vertices,
                                   trimesh.load(outs["folder"] / "frames" / f"frame_{k:04d}.obj", process=False).vertices,
                                   atol=1e-5)


def test_animate_job_quads_are_triangulated(inputs, tmp_path):
    quad = tmp_path / "quad.obj"  # a 2x1 grid of quads
    quad.write_text("v 0 0 0\nv 0.5 0 0\nv 1 0 0\nv 0 0 1\nv 0.5 0 1\nv 1 0 1\nf 1 2 5 4\nf 2 3 6 5\n")
    animate_main(["--checkpoint", inputs["checkpoint"], "--target", quad, "--driving",
                  str(inputs["driving"] / "frame_[0-4].obj"), "--out", tmp_path / "o", "--no-progress",
                  "--preview-frames", 0, "--force"])
    assert len(list((tmp_path / "o" / "frames").iterdir())) == 5
    assert read_glb(tmp_path / "o" / "animation.glb")["faces"].shape == (4, 3)


def _write(path: Path, data: str | bytes) -> Path:
    path.write_bytes(data if isinstance(data, bytes) else data.encode())
    return path


def _mkdir(path: Path) -> Path:
    path.mkdir()
    return path


def _driver_with(root: Path, name: str, data: str | bytes) -> Path:
    """A 3-frame driving folder with one extra file."""
    write_driver(root / "drv", 3)
    _write(root / "drv" / name, data)
    return root / "drv"


def _animated_glb(root: Path) -> bytes:
    return write_glb(root / "animated.glb", *driving_sequence(3)).read_bytes()


def _driver_then(root: Path, vertices: np.ndarray, faces: np.ndarray) -> Path:
    """A 3-frame driving folder whose second frame is another mesh."""
    write_driver(root / "drv", 3)
    trimesh.Trimesh(vertices, faces, process=False).export(root / "drv" / "frame_2.obj")
    return root / "drv"


def _ply_face_out_of_range(root: Path) -> Path:
    data = trimesh.Trimesh(*body(1), process=False).export(file_type="ply", encoding="ascii")
    return _write(root / "t.ply", data.replace(b"3 0 ", b"3 999 ", 1))


def _glb_over_2gib(root: Path) -> dict:
    big = trimesh.creation.icosphere(subdivisions=6)  # 40,962 vertices x 4,400 frames x 12 bytes > 2 GiB
    trimesh.Trimesh(big.vertices, big.faces, process=False).export(root / "big.ply")
    (root / "drv").mkdir()
    for k in range(4400):  # only counted before the refusal, never read
        (root / "drv" / f"f{k}.obj").touch()
    return {"target": root / "big.ply", "driving": root / "drv"}


def _checkpoint_of_another_config(root: Path, checkpoint: Path) -> Path:
    state = torch.load(checkpoint, weights_only=True)
    state["config"]["model"]["channels"] = [32]
    torch.save(state, root / "mismatch.pt")
    return root / "mismatch.pt"


def _out_not_empty(root: Path) -> dict:
    (root / "out").mkdir()
    _write(root / "out" / "keep.txt", "precious")
    return {}


TRIANGLE = "v 0 0 0\nv {} 0 0\nv 0 1 0\nf 1 2 {}\n"
# kind -> (root, inputs) -> (the inputs it replaces, extra arguments, a word its error line must contain)
BAD_CASES = {
    "missing target": lambda r, i: ({"target": r / "nope.obj"}, [], "no such file"),
    "missing driving": lambda r, i: ({"driving": r / "nope"}, [], "no file matches"),
    "empty driving dir": lambda r, i: ({"driving": _mkdir(r / "empty")}, [], "no mesh files"),
    "garbage bytes": lambda r, i: ({"driving": _driver_with(r, "frame_1.ply", os.urandom(300))}, [], "cannot read"),
    "garbage obj": lambda r, i: ({"target": _write(r / "g.obj", b"\x00\xff" * 50)}, [], "empty"),
    "unsupported format": lambda r, i: ({"target": _write(r / "t.txt", "v 0 0 0")}, [], "unsupported"),
    "fbx": lambda r, i: ({"target": _write(r / "t.fbx", b"Kaydara FBX Binary  \0")}, [],
                         "unsupported mesh format (use one of .obj, .ply, .off, .stl, .glb, .gltf): export it as glTF"),
    "bvh driver": lambda r, i: ({"driving": _write(r / "walk.bvh", "HIERARCHY\nROOT Hips\n")}, [],
                                "a BVH is a skeleton's motion without a mesh"),
    "empty file": lambda r, i: ({"driving": _driver_with(r, "frame_1.obj", b"")}, [], "empty"),
    "no vertices": lambda r, i: ({"driving": _driver_with(r, "frame_1.obj", "# only a comment\n")}, [], "empty"),
    "nan": lambda r, i: ({"driving": _driver_with(r, "frame_1.obj", TRIANGLE.format("nan", 3))}, [], "NaN"),
    "inf target": lambda r, i: ({"target": _write(r / "t.obj", TRIANGLE.format("inf", 3))}, [], "infinity"),
    "face out of range": lambda r, i: ({"target": _write(r / "t.obj", TRIANGLE.format(1, 9))}, [], "t.obj"),
    "face out of range ply": lambda r, i: ({"target": _ply_face_out_of_range(r)}, [], "out of range"),
    "mixed vertex counts": lambda r, i: ({"driving": _driver_then(r, *body(1))}, [], "frame_2.obj: 42 vertices"),
    "other faces": lambda r, i: ({"driving": _driver_then(r, body(2)[0], np.roll(body(2)[1], 1, axis=0))}, [],
                                 "frame_2.obj: other faces than the first driving frame"),
    "huge coordinates": lambda r, i: ({"target": _write(r / "t.obj", TRIANGLE.format("1e30", 3))}, ["--unit", "m"],
                                      "reaches 1e+30 m"),
    "huge coordinates, unit auto": lambda r, i: ({"target": _write(r / "t.obj", TRIANGLE.format("1e30", 3))}, [],
                                                 "1e+30 units across, a human body's size in none of m, cm, mm"),
    "no human size in any unit": lambda r, i: (
        {"target": _write(r / "t.obj", "v 0 0 0\nv 0 0 17\nv 0 1 0\nf 1 2 3\n")}, [], "17 units across"),
    "millimetres read as metres": lambda r, i: (
        {"target": _write(r / "t.obj", "v 0 0 0\nv 0 0 1700\nv 0 1 0\nf 1 2 3\n")}, ["--unit", "m"], "wrong --unit?"),
    "bad unit": lambda r, i: ({}, ["--unit", "inch"], "invalid choice: 'inch'"),
    "animated glb among frames": lambda r, i: ({"driving": _driver_with(r, "frame_9.glb", _animated_glb(r))}, [],
                                               "an animated glTF among 4 driving files"),
    "animation of frames": lambda r, i: ({}, ["--animation", "walk"], "plays an animation of one glTF --driving file"),
    "unknown animation": lambda r, i: ({"driving": _write(r / "c.glb", _animated_glb(r))}, ["--animation", "run"],
                                       "no animation 'run'; it has 'aniformer'"),
    "bad fps sidecar": lambda r, i: ({"driving": _driver_with(r, "sequence.json", '{"fps": "fast"}')}, [],
                                     "fps must be a positive number"),
    "too many morph targets": lambda r, i: ({}, ["--frames-per-mesh", "4096"],
                                            "cannot play more than 2,048 morph targets"),
    "glb over 2 GiB": lambda r, i: (_glb_over_2gib(r), [], "glTF clients load at most 2 GiB"),
    "over size limit": lambda r, i: ({}, ["--max-vertices", "500"], "exceeds the limit of 500"),
    "too many frames": lambda r, i: ({}, ["--max-frames", "10"], "exceeds --max-frames"),
    "garbage checkpoint": lambda r, i: ({"checkpoint": _write(r / "bad.pt", os.urandom(200))}, [],
                                        "not a readable checkpoint"),
    "checkpoint config mismatch": lambda r, i: ({"checkpoint": _checkpoint_of_another_config(r, i["checkpoint"])},
                                                [], "does not match its model config"),
    "missing checkpoint": lambda r, i: ({"checkpoint": r / "none.pt"}, [], "checkpoint not found"),
    "bad argument": lambda r, i: ({}, ["--batch-size", "0"], "--batch-size must be >= 1"),
    "bone names without a rig": lambda r, i: ({}, ["--bone-names", "mixamo"],
                                              "--bone-names names the rig's joints: add --rig"),
    "unknown option": lambda r, i: ({}, ["--frobnicate"], "unrecognized arguments"),
    "out not empty": lambda r, i: (_out_not_empty(r), [], "not empty"),
}


def _argv(args: dict, root: Path) -> list:
    return ["--checkpoint", args["checkpoint"], "--target", args["target"], "--driving", args["driving"],
            "--out", root / "out", "--no-progress"]


@pytest.mark.parametrize("kind", BAD_CASES)
def test_animate_bad_input_is_one_line_and_leaves_nothing(kind, inputs, tmp_path, capsys):
    replaced, extra, word = BAD_CASES[kind](tmp_path, inputs)
    argv = [*_argv({**inputs, **replaced}, tmp_path), *extra]
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


# Drops root's permission to read any file (CAP_DAC_OVERRIDE, CAP_DAC_READ_SEARCH) for the process it runs.
NO_DAC_OVERRIDE = ["setpriv", "--inh-caps=-dac_override,-dac_read_search",
                   "--bounding-set=-dac_override,-dac_read_search"]


@pytest.mark.parametrize("suffix", [".obj", ".ply"])  # our OBJ reader, trimesh
def test_animate_unreadable_file(inputs, tmp_path, suffix):
    """A mode-0 target: exit 2, one "cannot read" line. As a real process, without root's override under root."""
    target = tmp_path / f"t{suffix}"
    if suffix == ".obj":
        write_obj(target, *body(3))
    else:
        target.write_bytes(Path(inputs["target"]).read_bytes())
    target.chmod(0)
    argv = [sys.executable, str(ROOT / "jobs" / "animate.py"), *map(str, _argv({**inputs, "target": target}, tmp_path))]
    if os.geteuid() == 0:
        assert shutil.which("setpriv"), "setpriv (util-linux) is needed to test unreadable files as root"
        argv = NO_DAC_OVERRIDE + argv
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=120)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert lines[0].startswith(f"error: {target}: cannot read mesh") and "Permission denied" in lines[0], proc.stderr
    assert not (tmp_path / "out").exists()


def test_animate_refuses_nonempty_out_then_overwrites(inputs, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "old.txt").write_text("old")
    argv = _argv({**inputs, "driving": str(inputs["driving"] / "frame_[0-2].obj")}, tmp_path) + ["--preview-frames", "0",
                                                                                                 "--force"]
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
