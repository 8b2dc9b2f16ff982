"""jobs/animate.py --rig: rigged.glb (a skinned mesh, the clip as joint rotations) and motion.bvh, checked by
evaluating both files here, independently of aniformer/rig.py, against the animated frames."""

from __future__ import annotations

import dataclasses
import json
import re
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from aniformer.geometry import from_z_up
from aniformer.io.glb import read_document, to_gltf_axes
from aniformer.io.mesh import load_mesh

MODEL_TOPOLOGY = "notoes_collapse3pc"
FRAMES = 8


@pytest.fixture(scope="module")
def rigged(tmp_path_factory, job_main):
    """{name: output folder} of animate --rig with the shipped model on an 8-frame stream clip: ``anny`` (the
    clip's own target, an Anny mesh: no registration) and ``glb`` (a decimated body saved y-up as a GLB:
    registered; Mixamo's bone names)."""
    import trimesh

    from aniformer.cli.exits import run
    from aniformer.synth.variants import remesh

    root = tmp_path_factory.mktemp("rig")
    samples = root / "clip"
    run(job_main("export_meshes"), ["--stream", MODEL_TOPOLOGY, "--split", "crouch", "--frames", str(FRAMES),
                                    "--out", str(samples)])
    from aniformer.synth.bodies import BodyModel

    full = BodyModel("notoes")
    rest = full.pose(np.full((1, 6), 0.5, np.float32), np.zeros((1, len(full.bone_labels), 3), np.float32))[0]
    vertices, faces = remesh(rest, full.faces)
    trimesh.Trimesh(from_z_up(vertices, "y"), faces, process=False).export(root / "character.glb")
    outputs = {}
    for name, target in (("anny", samples / "target.obj"), ("glb", root / "character.glb")):
        outputs[name] = root / name
        run(job_main("animate"), ["--target", str(target), "--driving", str(samples / "driving"), "--out",
                                  str(outputs[name]), "--no-progress", "--preview-frames", "0", "--rig",
                                  "--bone-names", {"anny": "anny", "glb": "mixamo"}[name]])
    return outputs


def evaluate_rig(path: Path) -> dict:
    """The skinned vertices and joint positions a glTF client computes for every frame, from the file
    alone: node TRS at each STEP key, the joint hierarchy, inverse bind matrices, JOINTS_0 / WEIGHTS_0."""
    gltf, accessor = read_document(path)
    nodes, skin = gltf["nodes"], gltf["skins"][0]
    primitive = gltf["meshes"][0]["primitives"][0]
    bind = accessor(primitive["attributes"]["POSITION"]).astype(np.float64)
    joints = accessor(primitive["attributes"]["JOINTS_0"]).astype(np.int64)
    weights = accessor(primitive["attributes"]["WEIGHTS_0"]).astype(np.float64)
    inverse_bind = accessor(skin["inverseBindMatrices"]).reshape(-1, 4, 4).transpose(0, 2, 1).astype(np.float64)
    frames = gltf["animations"][0]["extras"]["frames"]
    trs = {i: {"translation": np.tile(n.get("translation", [0, 0, 0]), (frames, 1)),
               "rotation": np.tile(n.get("rotation", [0, 0, 0, 1]), (frames, 1))} for i, n in enumerate(nodes)}
    for channel in gltf["animations"][0]["channels"]:
        sampler = gltf["animations"][0]["samplers"][channel["sampler"]]
        assert sampler["interpolation"] == "STEP"
        trs[channel["target"]["node"]][channel["target"]["path"]] = accessor(sampler["output"])[:frames]
    parent = {c: i for i, n in enumerate(nodes) for c in n.get("children", [])}

    def world(i: int) -> np.ndarray:
        local = np.tile(np.eye(4), (frames, 1, 1))
        local[:, :3, :3] = Rotation.from_quat(trs[i]["rotation"]).as_matrix()
        local[:, :3, 3] = trs[i]["translation"]
        return local if i not in parent else world(parent[i]) @ local

    joint_world = np.stack([world(j) for j in skin["joints"]], 1)  # (N, J, 4, 4)
    skinning = joint_world @ inverse_bind
    per_vertex = skinning[:, joints]  # (N, V, 4, 4, 4)
    moved = np.einsum("nvkab,vb->nvka", per_vertex[..., :3, :3], bind) + per_vertex[..., :3, 3]
    return {"gltf": gltf, "skinned": (weights[None, ..., None] * moved).sum(2), "joints": joint_world[..., :3, 3],
            "names": [nodes[j]["name"] for j in skin["joints"]], "weights": weights, "primitive": primitive}


def frames_in_gltf_axes(out: Path) -> np.ndarray:
    """frames/*.obj (in the target's axes) in glTF's y-up axes."""
    summary = json.loads((out / "animation.json").read_text())
    frames = np.stack([load_mesh(p)[0] for p in sorted((out / "frames").glob("*.obj"))]).astype(np.float64)
    return frames if summary["up"]["target"]["axis"] == "y" else to_gltf_axes(frames)


@pytest.mark.parametrize("name", ["anny", "glb"])
def test_rigged_glb_skins_into_the_animated_frames(rigged, name):
    """No morph targets, >= 20 joints, 4 normalised weights per vertex; the skinning a client computes from the
    file alone reproduces frames/*.obj to the residual animation.json reports, well under the model's error."""
    rig = evaluate_rig(rigged[name] / "rigged.glb")
    assert "targets" not in rig["primitive"] and len(rig["names"]) >= 20
    assert rig["names"][0] == {"anny": "root", "glb": "mixamorig:Hips"}[name]
    assert rig["weights"].shape[1] == 4 and np.abs(rig["weights"].sum(1) - 1).max() < 1e-6
    frames = frames_in_gltf_axes(rigged[name])
    assert rig["skinned"].shape == frames.shape
    rms = float(np.sqrt(np.square(rig["skinned"] - frames).sum(-1).mean()))
    summary = json.loads((rigged[name] / "animation.json").read_text())
    assert summary["rig"]["joints"] == len(rig["names"])
    assert rms == pytest.approx(summary["rig"]["residual_m"], abs=2e-4) and rms < 0.03


def parse_bvh(path: Path) -> dict:
    """{names, parents, offsets (J, 3), channels per joint, motion (N, columns), frame time} of a BVH file."""
    text = path.read_text()
    names, parents, offsets, channels, stack, last = [], [], [], [], [], None
    lines = iter(text.split("MOTION")[0].splitlines()[1:])
    for line in lines:
        words = line.split()
        if words[0] in ("ROOT", "JOINT"):
            names.append(words[1])
            parents.append(stack[-1] if stack else -1)
            last = len(names) - 1
        elif words[0] == "End":
            next(lines), next(lines), next(lines)  # {, OFFSET, }
        elif words[0] == "{":
            stack.append(last)
        elif words[0] == "}":
            stack.pop()
        elif words[0] == "OFFSET":
            offsets.append([float(w) for w in words[1:]])
        elif words[0] == "CHANNELS":
            channels.append(words[2:])
    motion = text.split("MOTION")[1].splitlines()
    frames = int(re.match(r"Frames:\s*(\d+)", motion[1]).group(1))
    frame_time = float(re.match(r"Frame Time:\s*([\d.]+)", motion[2]).group(1))
    rows = np.array([[float(v) for v in row.split()] for row in motion[3:] if row.strip()])
    assert len(rows) == frames
    return {"names": names, "parents": parents, "offsets": np.array(offsets), "channels": channels, "motion": rows,
            "frame_time": frame_time}


def test_fitted_weights_are_the_ones_that_skinned_the_frames():
    """Frames skinned from an Anny body with known joint turns (24 frames) and weights moved off Anny's (the same
    bones, each weight x0.5-1.5): ``fit_weights`` under that motion finds those weights, not Anny's, as far as
    the frames tell them apart (module doc, step 4)."""
    import torch

    from aniformer.rig import build_rig, forward_kinematics, skin
    from aniformer.rig_motion import RigMotion, fit_weights
    from aniformer.synth.bodies import BodyModel

    body = BodyModel(MODEL_TOPOLOGY)
    rest = body.pose(np.full((1, 6), 0.5, np.float32), np.zeros((1, len(body.bone_labels), 3), np.float32))[0]
    rig = build_rig(rest, rest, MODEL_TOPOLOGY)
    rng = np.random.default_rng(0)
    turns = Rotation.from_rotvec(rng.normal(0, 0.5, (3 * FRAMES * len(rig.names), 3))).as_matrix()
    rotations = torch.from_numpy(rig.local_bind[None, :, :3, :3] @ turns.reshape(3 * FRAMES, len(rig.names), 3, 3))
    world = forward_kinematics(rig, rotations, torch.from_numpy(np.tile(rig.bind[0, :3, 3], (3 * FRAMES, 1))))
    moved = rig.weights * rng.uniform(0.5, 1.5, rig.weights.shape)
    truth = dataclasses.replace(rig, weights=(moved / moved.sum(1, keepdims=True)).astype(np.float32))
    frames = skin(truth, rest, world).numpy()
    motion = RigMotion(np.zeros((3 * FRAMES, len(rig.names), 4)), np.zeros((3 * FRAMES, 3)), world.numpy(), 0.0)
    fitted = fit_weights(rig, rest, motion, frames)
    assert (fitted.weights >= 0).all() and np.abs(fitted.weights.sum(1) - 1).max() < 1e-6

    def per_bone(weights):  # (V, J)
        dense = np.zeros((len(rest), len(weights.names)))
        np.add.at(dense, (np.arange(len(rest))[:, None], weights.joints.astype(np.int64)), weights.weights)
        return dense

    assert not (per_bone(fitted)[per_bone(truth) == 0] > 0).any()  # no bone a vertex had no weight on
    assert np.abs(per_bone(fitted) - per_bone(truth)).sum() < 0.3 * np.abs(per_bone(rig) - per_bone(truth)).sum()

    def residual(weights):
        return np.sqrt(np.square(skin(weights, rest, world).numpy() - frames).sum(-1).mean())

    assert residual(fitted) < 0.1 * residual(rig)  # 0.26 mm against 4.9 (the prior's pull keeps a little)


@pytest.mark.parametrize("name", ["anny", "glb"])
def test_bvh_moves_the_same_joints_as_the_rigged_glb(rigged, name):
    """A HIERARCHY of the rig's joints and one MOTION row per frame; its joints, posed by its own offsets and
    ZXY Euler angles, are where rigged.glb puts them."""
    bvh = parse_bvh(rigged[name] / "motion.bvh")
    rig = evaluate_rig(rigged[name] / "rigged.glb")
    assert sorted(bvh["names"]) == sorted(rig["names"]) and len(bvh["motion"]) == FRAMES
    assert bvh["frame_time"] == pytest.approx(1 / 30, rel=1e-6)
    assert bvh["channels"][0][:3] == ["Xposition", "Yposition", "Zposition"]
    assert all(c[-3:] == ["Zrotation", "Xrotation", "Yrotation"] for c in bvh["channels"])
    position, rotation, column = {}, {}, 0
    for j, parent in enumerate(bvh["parents"]):
        values = bvh["motion"][:, column:column + len(bvh["channels"][j])]
        column += len(bvh["channels"][j])
        turn = Rotation.from_euler("ZXY", values[:, -3:], degrees=True).as_matrix()
        if parent < 0:
            position[j], rotation[j] = values[:, :3] + bvh["offsets"][j], turn
        else:
            position[j] = position[parent] + np.einsum("nab,b->na", rotation[parent], bvh["offsets"][j])
            rotation[j] = rotation[parent] @ turn
    for j, joint in enumerate(bvh["names"]):  # the unit is metres here (--unit m)
        np.testing.assert_allclose(position[j], rig["joints"][:, rig["names"].index(joint)], atol=1e-4)


def test_mixamo_bone_names_name_the_mixamo_skeleton(rigged):
    """--bone-names mixamo: Mixamo's chains from the hips to the hands, head and feet, each joint below the
    one Mixamo puts it under (Anny's extra bones between them), Left on the character's left (+x: glTF
    characters face +z), and the same joints as Anny's names give."""
    rig, anny = evaluate_rig(rigged["glb"] / "rigged.glb"), evaluate_rig(rigged["anny"] / "rigged.glb")
    nodes, names = rig["gltf"]["nodes"], rig["names"]
    parent = {c: i for i, n in enumerate(nodes) for c in n.get("children", [])}

    def ancestors(name):
        i, found = [n["name"] for n in nodes].index(name), []
        while i in parent:
            i = parent[i]
            found.append(nodes[i]["name"])
        return found

    chains = [["Hips", "Spine", "Spine1", "Spine2", "Neck", "Head"]] + [
        [*(["Hips", "Spine", "Spine1", "Spine2"] if limb == "arm" else ["Hips"]), *(f"{side}{b}" for b in bones)]
        for side in ("Left", "Right") for limb, bones in (("arm", ("Shoulder", "Arm", "ForeArm", "Hand", "HandIndex1")),
                                                          ("leg", ("UpLeg", "Leg", "Foot")))]
    for chain in chains:
        for above, below in zip(chain, chain[1:]):
            assert f"mixamorig:{above}" in ancestors(f"mixamorig:{below}"), (above, below)
    bind = {name: rig["joints"][0, names.index(f"mixamorig:{name}")]
            for name in ("LeftHand", "RightHand", "LeftFoot", "RightFoot")}
    assert bind["LeftHand"][0] > bind["RightHand"][0] and bind["LeftFoot"][0] > bind["RightFoot"][0]
    assert len(names) == len(anny["names"]) and "mixamorig:Hips" == names[0] and "root" == anny["names"][0]


def test_rigged_glb_passes_the_khronos_validator(rigged):
    from test_animate import VALIDATOR_READY, khronos_reports

    if not VALIDATOR_READY:
        pytest.skip("no node or gltf-validator: npm ci --prefix tests/js")
    for report in khronos_reports([rigged[name] / "rigged.glb" for name in rigged]):
        assert report["numErrors"] == 0 and report["numWarnings"] == 0, report


def test_threejs_plays_the_skinned_mesh(rigged, tmp_path):
    """three.js loads rigged.glb as a SkinnedMesh with every joint as a bone and no morph targets, and the
    skinned body it draws at the last frame stands where frames/*.obj puts it."""
    from test_animate import THREE_READY, body_pixels, play_in_threejs

    if not THREE_READY:
        pytest.skip("no chromium or three: .ci/run installs both")
    out = rigged["glb"]
    summary = json.loads((out / "animation.json").read_text())
    result, shot = play_in_threejs(out / "rigged.glb", FRAMES - 1, summary["fps"], tmp_path / "www")
    assert result["morphs"] == 0 and result["bones"] == summary["rig"]["joints"]
    assert result["duration"] == pytest.approx(FRAMES / summary["fps"], rel=1e-4)
    last = frames_in_gltf_axes(out)[-1]
    np.testing.assert_allclose(result["now"]["min"], last.min(0), atol=0.05)
    np.testing.assert_allclose(result["now"]["max"], last.max(0), atol=0.05)
    assert body_pixels(shot) > 500


@pytest.mark.parametrize("name", ["anny", "glb"])
def test_blender_imports_the_rig_and_the_bvh(rigged, name, tmp_path):
    """bench/blender_rig.py in Debian's Blender, for the Anny target and the y-up GLB character (Mixamo names):
    rigged.glb is one armature of every joint skinning the mesh (no shape keys), its action spans the clip, the
    skinned mesh is the job's frames to the reported residual at every frame; motion.bvh is an armature of as
    many bones with an action of the clip's frames."""
    import shutil
    import subprocess

    blender = shutil.which("blender")
    if blender is None:
        pytest.skip("no blender on PATH (.ci/run installs Debian's blender)")
    report = tmp_path / "report.json"
    proc = subprocess.run([blender, "-b", "--factory-startup", "--python-exit-code", "1", "--python",
                           str(Path(__file__).resolve().parents[1] / "bench" / "blender_rig.py"), "--",
                           str(rigged[name]), "--json", str(report)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    result = json.loads(report.read_text())
    joints = json.loads((rigged[name] / "animation.json").read_text())["rig"]["joints"]
    assert result["gltf"]["bones"] == [joints] and result["bvh"]["bones"] == [joints] and not result["failures"]
