"""Wall time, frames/s and peak RSS of ``jobs/animate.py`` by stage, for targets of 369 to ~150k vertices.

Run from the repository root (minutes per checkout on 2 cores):

    python bench/animate_bench.py --out bench/results/animate_bench.json
    python bench/animate_bench.py --checkout before=/tmp/baseline --checkout after=.   # side by side
    python bench/animate_bench.py --targets 369 18k --frames 300 --rig   # also rigged.glb and motion.bvh
    python bench/animate_bench.py --targets 18k --frames 300 --warm-fit   # the target's fit kept from a run before
    python bench/animate_bench.py --checkpoints pretrained skinned --targets 369 --frames 30   # network or skinned

Inputs, made here and shared by every checkout so the runs differ only in code:
- a driving clip on Anny's 369-vertex topology (``jumping_jacks``, 30 or 300 frames, OBJ files);
- targets: another Anny identity at 369 and 1,229 vertices (no registration: the model's topologies),
  and the 12,272-vertex Anny body subdivided at edge midpoints to ~18k, ~72k and ~150k vertices (a
  foreign topology: registered, as an artist's character would be).

Each run is one ``jobs/animate.py`` process (``--no-progress``), as a user starts it; its peak RSS is
the process's ``ru_maxrss`` (``os.wait4``), its stage times the ``seconds`` of animation.json; with
``--rig`` each row also has the sizes of animation.glb, rigged.glb and motion.bvh. Every run registers
afresh (an empty ``ANIFORMER_CACHE_DIR`` of its own), unless ``--warm-fit``: then each target is animated
once untimed first, and the timed run loads that fit (``aniformer.registration.cached_fit``).
"""

from __future__ import annotations

import argparse
import functools
import itertools
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import trimesh

REPO = Path(__file__).resolve().parents[1]

TARGETS = {"369": 369, "1.2k": 1_229, "18k": 18_000, "72k": 72_000, "150k": 150_000}
CLIPS = (30, 300)


def subdivided(vertices: np.ndarray, faces: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """The mesh subdivided at edge midpoints, largest faces first, until it has about ``count`` vertices."""
    while len(vertices) < count:
        # a face split adds ~1.5 vertices (3 edge midpoints, each shared by two faces)
        split = min(len(faces), int((count - len(vertices)) / 1.5) + 1)
        largest = np.argsort(trimesh.triangles.area(vertices[faces]))[-split:]
        vertices, faces = trimesh.remesh.subdivide(vertices, faces, largest)
    return vertices, faces


def make_inputs(root: Path, frames: int, targets: list[str]) -> dict[str, Path]:
    """The driving clip (``root/clip_<frames>/``) and the target meshes (``root/target_<name>.obj``)."""
    from aniformer.io.mesh import write_obj
    from aniformer.synth.bodies import BodyModel, sample_identities
    from aniformer.synth.motions import sample_motion

    clip = root / f"clip_{frames}"
    if not clip.exists():
        body = BodyModel("notoes_collapse3pc")
        motion = sample_motion("jumping_jacks", seed=0, bone_labels=body.bone_labels, frames=frames)
        driving = body.pose(np.repeat(sample_identities(1, seed=0), frames, 0), motion.rotvecs, motion.translation)
        clip.mkdir(parents=True)
        for k, vertices in enumerate(driving):
            write_obj(clip / f"frame_{k:04d}.obj", vertices, body.faces)
    paths = {"clip": clip}
    identity = sample_identities(2, seed=0)[1:]
    for name in targets:
        path = paths[name] = root / f"target_{name}.obj"
        if path.exists():
            continue
        topology = {"369": "notoes_collapse3pc", "1.2k": "notoes_collapse10pc"}.get(name, "notoes")
        body = BodyModel(topology)
        vertices = body.pose(identity, np.zeros((1, len(body.bone_labels), 3), np.float32))[0].astype(np.float64)
        faces = body.faces
        if topology == "notoes":
            vertices, faces = subdivided(vertices, faces, TARGETS[name])
        write_obj(path, vertices, faces)
    return paths


def run_animate(checkout: Path, target: Path, clip: Path, out: Path, fit_cache: Path, rig: bool = False,
                checkpoint: str = "pretrained") -> dict:
    """One animate process of ``checkpoint``, registering with the fits kept in ``fit_cache``: its animation.json's
    stage seconds, wall time and peak RSS (and output sizes)."""
    env = {**os.environ, "PYTHONPATH": str(checkout), "ANIFORMER_CACHE_DIR": str(fit_cache)}  # the checkout's package
    command = [sys.executable, str(checkout / "jobs" / "animate.py"), "--checkpoint", checkpoint, "--target", str(target),
               "--driving", str(clip), "--out", str(out), "--overwrite", "--no-progress", *(["--rig"] if rig else [])]
    began = time.perf_counter()
    process = subprocess.Popen(command, env=env, cwd=checkout, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    output = process.stdout.read().decode()
    _, status, usage = os.wait4(process.pid, 0)
    wall = time.perf_counter() - began
    if status != 0:
        raise RuntimeError(f"{' '.join(command)} failed:\n{output[-2000:]}")
    summary = json.loads((out / "animation.json").read_text())
    written = ("animation.glb", "rigged.glb", "motion.bvh") if rig else ()
    sizes = {f"{name}_mb": round((out / name).stat().st_size / 2**20, 3) for name in written}
    return {"wall_s": round(wall, 2), "peak_rss_gb": round(usage.ru_maxrss / 2**20, 3),
            "frames": summary["frames"], "seconds": summary["seconds"], **summary.get("rig", {}), **sizes}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkout", action="append", default=[],
                   help="NAME=PATH of a repository checkout to time (repeat; default: this one as 'now')")
    p.add_argument("--targets", nargs="+", default=list(TARGETS), choices=list(TARGETS))
    p.add_argument("--frames", nargs="+", type=int, default=list(CLIPS))
    p.add_argument("--inputs", type=Path, help="folder for the generated inputs (kept; default: a temp folder)")
    p.add_argument("--rig", action="store_true", help="animate with --rig, and report the output files' sizes")
    p.add_argument("--warm-fit", action="store_true",
                   help="time each target with its registration kept from an untimed run before (default: afresh)")
    p.add_argument("--checkpoints", nargs="+", default=["pretrained"],
                   help="jobs/animate.py's --checkpoint of each run (default: pretrained)")
    p.add_argument("--out", type=Path, help="write the rows as JSON here")
    args = p.parse_args()
    checkouts = dict(c.split("=", 1) for c in args.checkout) or {"now": str(REPO)}
    rows = []
    with tempfile.TemporaryDirectory(prefix="aniformer-bench-") as scratch:
        root = args.inputs or Path(scratch)
        for frames in args.frames:
            inputs = make_inputs(root, frames, args.targets)
            for name in args.targets:
                for (label, checkout), checkpoint in itertools.product(checkouts.items(), args.checkpoints):
                    fit_cache = Path(tempfile.mkdtemp(prefix=f"fits-{label}-", dir=scratch))
                    run = functools.partial(run_animate, Path(checkout).resolve(), inputs[name], inputs["clip"],
                                            Path(scratch) / "out", fit_cache, args.rig, checkpoint)
                    if args.warm_fit:
                        run()
                    row = {"checkout": label, "checkpoint": checkpoint, "target": name, "frames": frames,
                           "fit": "warm" if args.warm_fit else "cold", **run()}
                    row["fps_end_to_end"] = round(frames / row["wall_s"], 2)
                    print(json.dumps(row), flush=True)
                    rows.append(row)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
