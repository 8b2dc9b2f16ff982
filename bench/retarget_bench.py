"""Pairs/s and frames/s of one jobs/retarget.py job against sequential jobs/animate.py calls on the same pairs,
on 1 and 2 CPUs (``taskset``: the processes and every Ray worker they start are pinned to them).

Run from the repository root (about 6 minutes on 2 cores):

    python bench/retarget_bench.py --out bench/results/retarget_bench.json

The library, made here: targets ``anny`` (Anny's 369-vertex topology, the shipped model's) and
``decimated`` (a body of another topology, registered); clips ``walk`` and ``crouch`` (Anny, 30 frames)
and ``shuffled_walk`` (``walk`` with its vertices in another order: registered). 2 x 3 = 6 pairs, 180
frames. Sequential animate registers the decimated target for each of its 3 pairs and the shuffled clip
for each of its 2; retarget registers each once. Each measurement is the wall time of its processes,
start-up included (animate: one process per pair; retarget: one process that starts its local Ray with
``num_cpus`` = the CPUs, as `pipeline.cluster.connect` would with all of them).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
FRAMES = 30
TOPOLOGY = "notoes_collapse3pc"


def make_library(root: Path) -> tuple[Path, Path]:
    """targets/ and clips/ of the module docstring under ``root``."""
    import numpy as np
    import trimesh

    from aniformer.io.mesh import load_mesh
    from aniformer.synth.stream import StreamPairs, _body_model, pose_pairs
    from aniformer.synth.variants import remesh

    exported = {}
    for split in ("locomotion", "crouch"):
        exported[split] = root / "export" / split
        subprocess.run([sys.executable, str(REPO / "jobs" / "export_meshes.py"), "--stream", TOPOLOGY, "--split",
                        split, "--frames", str(FRAMES), "--out", str(exported[split])], check=True,
                       stdout=subprocess.DEVNULL)
    targets, clips = root / "targets", root / "clips"
    targets.mkdir()
    shutil.copy(exported["locomotion"] / "target.obj", targets / "anny.obj")
    full = _body_model("notoes")
    body = pose_pairs(full, StreamPairs(TOPOLOGY, window=1, seed=5).draws("characters", 0, [0]))[2][0, 0]
    trimesh.Trimesh(*remesh(body, full.faces), process=False).export(targets / "decimated.obj")
    shutil.copytree(exported["locomotion"] / "driving", clips / "walk")
    shutil.copytree(exported["crouch"] / "driving", clips / "crouch")
    order = np.random.default_rng(1).permutation(369)
    (clips / "shuffled_walk").mkdir()
    for frame in sorted((clips / "walk").glob("*.obj")):
        vertices, faces = load_mesh(frame)
        trimesh.Trimesh(vertices[order], np.argsort(order)[faces], process=False).export(
            clips / "shuffled_walk" / frame.name)
    return targets, clips


def pinned(cpus: int) -> list[str]:
    return ["taskset", "-c", ",".join(str(c) for c in range(cpus))]


def sequential_animate(targets: Path, clips: Path, out: Path, cpus: int) -> float:
    """Seconds for one jobs/animate.py process per pair, one after the other."""
    began = time.perf_counter()
    for target in sorted(targets.iterdir()):
        for clip in sorted(clips.iterdir()):
            subprocess.run([*pinned(cpus), sys.executable, str(REPO / "jobs" / "animate.py"), "--target", str(target),
                            "--driving", str(clip), "--out", str(out / target.stem / clip.name), "--no-progress"],
                           check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - began


def one_retarget_job(targets: Path, clips: Path, out: Path, cpus: int) -> float:
    """Seconds for one jobs/retarget.py job on a local Ray of ``cpus`` CPUs (this script with --job)."""
    began = time.perf_counter()
    subprocess.run([*pinned(cpus), sys.executable, __file__, "--job", str(cpus), "--", "--targets", str(targets),
                    "--clips", str(clips), "--out", str(out), "--no-progress", "--no-mlflow"],
                   check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - began


def run_job(cpus: int, argv: list[str]) -> None:
    """jobs/retarget.py's main on a local Ray started here with ``cpus`` CPUs (connect() then joins it)."""
    import ray

    from aniformer.cli.exits import run
    from jobs.retarget import main
    from pipeline.cluster import LOCALHOST, _local_node_only

    _local_node_only()  # on 127.0.0.1 only, as connect()'s own local Ray
    ray.init(address="local", num_cpus=cpus, include_dashboard=False, _node_ip_address=LOCALHOST)
    run(main, argv)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, help="JSON of the results")
    parser.add_argument("--cpus", default="1,2", help="CPU counts (default 1,2)")
    parser.add_argument("--job", type=int, metavar="CPUS", help=argparse.SUPPRESS)  # one_retarget_job's process
    args, rest = parser.parse_known_args()
    if args.job:
        return run_job(args.job, [a for a in rest if a != "--"])
    results = []
    with tempfile.TemporaryDirectory(prefix="retarget-bench-") as scratch:
        targets, clips = make_library(Path(scratch))
        pairs = len(list(targets.iterdir())) * len(list(clips.iterdir()))
        frames = pairs * FRAMES
        for cpus in (int(c) for c in args.cpus.split(",")):
            for way, measure in (("sequential animate", sequential_animate), ("retarget", one_retarget_job)):
                seconds = measure(targets, clips, Path(scratch) / f"{way}-{cpus}".replace(" ", "_"), cpus)
                results.append({"cpus": cpus, "way": way, "pairs": pairs, "frames": frames,
                                "seconds": round(seconds, 1), "pairs_per_s": round(pairs / seconds, 3),
                                "frames_per_s": round(frames / seconds, 2)})
                print(f"{cpus} CPU  {way:<18} {pairs} pairs {seconds:6.1f} s  {pairs / seconds:.3f} pairs/s  "
                      f"{frames / seconds:.2f} frames/s", flush=True)
    record = {"date": time.strftime("%Y-%m-%d"), "machine": f"{platform.machine()}, {os.cpu_count()} cores",
              "results": results}
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(record, indent=2) + "\n")


if __name__ == "__main__":
    main()
