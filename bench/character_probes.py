"""Characters outside the evaluated variants, animated through jobs/animate.py as a user would: what it does.

    python bench/character_probes.py --out bench/results/probes

From ``bench/animate_bench.py``'s 18k-vertex character (a foreign topology, z up, at rest) and its
jumping-jacks clip (every 5th of 300 frames: one whole jump), five characters a studio brings:

- ``holes``: a scan with holes (faces within 3 cm of 30 random vertices removed, 17% of them);
- ``stylised``: legs 0.85x as long, head 1.25x as large (a cartoon's proportions, mildly);
- ``chibi``: legs 0.65x, head 1.5x (beyond Anny's shape space);
- ``sword``: holding a 0.9 m sword, a separate part (a prop);
- ``skirt``: a flared skirt, a separate part covering the thighs (loose clothing).

Each runs ``jobs/animate.py`` (the shipped model, its defaults) in a cache of its own; the table gives
its exit status, the self-check's verdict, and the registration line. There is no ground truth for
these: look at the filmstrip (``--png``, rows: driver, then each result, forced where refused).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import trimesh

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "bench"))


def proportions(vertices: np.ndarray, legs: float, head: float) -> np.ndarray:
    """The body with its legs (below 47% of its height) ``legs`` times as long and its head (above 87%) scaled."""
    out, bottom, height = vertices.copy(), vertices[:, 2].min(), np.ptp(vertices[:, 2])
    crotch, neck = bottom + 0.47 * height, bottom + 0.87 * height
    low, high = vertices[:, 2] < crotch, vertices[:, 2] > neck
    out[low, 2] = crotch - (crotch - vertices[low, 2]) * legs
    centre = np.array([vertices[high, 0].mean(), vertices[high, 1].mean(), neck])
    out[high] = centre + (vertices[high] - centre) * head
    return out


def with_part(vertices: np.ndarray, faces: np.ndarray, part: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray]:
    return np.concatenate([vertices, part.vertices]), np.concatenate([faces, part.faces + len(vertices)])


def skirt(vertices: np.ndarray) -> trimesh.Trimesh:
    """An open cone from the hips (53% of the height) flaring 15 cm over 35 cm down."""
    bottom, height = vertices[:, 2].min(), np.ptp(vertices[:, 2])
    hip = bottom + 0.53 * height
    ring = vertices[np.abs(vertices[:, 2] - hip) < 0.02, :2]
    centre = ring.mean(0)
    radius = np.linalg.norm(ring - centre, axis=1).max() + 0.02
    angles, levels = np.linspace(0, 2 * np.pi, 48, endpoint=False), np.linspace(0, 1, 10)
    points = np.array([[*(centre + (radius + 0.15 * t) * np.array([np.cos(a), np.sin(a)])), hip - 0.35 * t]
                       for t in levels for a in angles])
    quads = [(i * 48 + j, (i + 1) * 48 + j, i * 48 + (j + 1) % 48, (i + 1) * 48 + (j + 1) % 48)
             for i in range(len(levels) - 1) for j in range(48)]
    faces = [f for a, c, b, d in quads for f in ((a, c, b), (b, c, d))]
    return trimesh.Trimesh(points, faces, process=False)


def characters(vertices: np.ndarray, faces: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(0)
    centres = vertices[rng.choice(len(vertices), 30)]
    holed = (np.linalg.norm(vertices[faces].mean(1)[:, None] - centres[None], axis=2) < 0.03).any(1)
    hand = vertices[vertices[:, 0].argmin()]  # a hand's farthest point, arms down in an A pose
    sword = trimesh.creation.box(extents=[0.03, 0.03, 0.9])
    sword.apply_translation(hand + [0.0, -0.05, -0.4])
    return {"holes": (vertices, faces[~holed]),
            "stylised": (proportions(vertices, 0.85, 1.25), faces),
            "chibi": (proportions(vertices, 0.65, 1.5), faces),
            "sword": with_part(vertices, faces, sword),
            "skirt": with_part(vertices, faces, skirt(vertices))}


def main() -> None:
    from animate_bench import make_inputs

    from aniformer.animate import driving_files, load_driving
    from aniformer.io.mesh import write_obj
    from aniformer.io.render import render_filmstrip

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--png", type=Path, help="a filmstrip of the driver and every result")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    inputs = make_inputs(args.out, 300, ["18k"])
    clip = args.out / "clip_jump"
    clip.mkdir(exist_ok=True)
    for k, frame in enumerate(sorted(inputs["clip"].glob("*.obj"))[::5]):
        link = clip / f"frame_{k:04d}.obj"
        if not link.exists():
            link.symlink_to(frame.resolve())
    body = trimesh.load(inputs["18k"], process=False)
    driving, driving_faces = load_driving(driving_files(str(clip)), 10**6, "m")
    rows = [("driver", driving, driving_faces)]
    print("| character | vertices | exit | self-check | registration |\n|---|---:|---:|---|---|")
    for name, (vertices, faces) in characters(np.asarray(body.vertices), np.asarray(body.faces)).items():
        write_obj(args.out / f"{name}.obj", vertices, faces)
        command = [sys.executable, str(REPO / "jobs" / "animate.py"), "--target", str(args.out / f"{name}.obj"),
                   "--driving", str(clip), "--out", str(args.out / name), "--overwrite", "--no-progress"]
        env = {**os.environ, "ANIFORMER_CACHE_DIR": str(args.out / "cache" / name)}
        run = subprocess.run(command, capture_output=True, text=True, env=env, cwd=REPO)
        lines = (run.stdout + run.stderr).splitlines()
        verdict = next((line for line in lines if line.startswith(("self-check", "error"))), "")
        registered = next((line.split(": ", 1)[1] for line in lines if line.startswith("registered")), "")
        print(f"| {name} | {len(vertices):,} | {run.returncode} | {verdict[:160]} | {registered} |", flush=True)
        if args.png:
            if run.returncode:
                subprocess.run([*command, "--force"], capture_output=True, env=env, cwd=REPO, check=True)
            frames = sorted((args.out / name / "frames").glob("*.obj"))
            meshes = [trimesh.load(f, process=False) for f in frames]  # an OBJ's unused vertices are not read back
            rows.append((name + (" (refused; forced)" if run.returncode else ""), np.stack([m.vertices for m in meshes]),
                         meshes[0].faces))
    if args.png:
        render_filmstrip(rows, args.png, frames=8, panel_px=160)


if __name__ == "__main__":
    main()
