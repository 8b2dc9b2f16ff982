"""Deformation transfer's Laplacian solve, sparse (aniformer.transfer) against the dense Cholesky it replaced:
factorisation time, solve time per frame, the factor's size and the process's peak RSS, on Anny's topologies
and the 12,272-vertex body subdivided to ~50k vertices.

Run from the repository root (a few minutes on 2 cores; the dense solve is skipped above 13k vertices,
where it needs V^2 x 8 bytes twice over: 20 GB at 50k):

    python bench/transfer_bench.py --out bench/results/transfer_bench.json

Each (solver, mesh) runs in its own process, so its peak RSS is its own.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]

MESHES = {"369": "notoes_collapse3pc", "1.2k": "notoes_collapse10pc", "12k": "notoes", "50k": "notoes"}
DENSE_LIMIT = 13_000
FRAMES = 24  # a batch of 8 windows of T = 3


def one(solver: str, mesh: str) -> dict:
    """Time and memory of one solver on one mesh, in this process."""
    import torch
    from animate_bench import subdivided

    from aniformer import transfer
    from aniformer.surface import closest_points
    from aniformer.synth.bodies import BodyModel, sample_identities
    from aniformer.synth.motions import sample_motion

    body = BodyModel(MESHES[mesh])
    motion = sample_motion("punching", seed=0, bone_labels=body.bone_labels, frames=FRAMES)
    identities = sample_identities(2, seed=0)
    driving = body.pose(np.repeat(identities[:1], FRAMES, 0), motion.rotvecs, motion.translation)
    target = body.pose(identities[1:], np.zeros((1, len(body.bone_labels), 3), np.float32))[0]
    faces = body.faces
    if mesh == "50k":  # the target subdivided; each driving frame alike (midpoints are barycentric points)
        vertices, faces = subdivided(target.astype(np.float64), faces, 50_000)
        driving = closest_points(vertices, target.astype(np.float64), body.faces).on(driving, body.faces)
        target = vertices.astype(np.float32)
    V = len(target)
    driving_t, target_t = torch.from_numpy(driving[None]).float(), torch.from_numpy(target[None]).float()
    faces_t = torch.from_numpy(np.asarray(faces, np.int64))
    began = time.perf_counter()
    if solver == "sparse":
        _, _, factor = transfer._topology(faces_t.numpy().tobytes(), len(faces_t), V)
        factor_bytes = (factor.L.nnz + factor.U.nnz) * 12  # float64 value + int32 index
        factorised = time.perf_counter() - began
        began = time.perf_counter()
        transfer.deformation_transfer(driving_t, target_t, faces_t)
        solved = time.perf_counter() - began
    else:
        from test_transfer import dense_transfer  # the reference the tests compare with

        # one frame: cholesky_solve broadcasts the V x V factor over a batch's frames (28 GB for 24 at 12k)
        dense_transfer(driving_t[:, :1], target_t, np.asarray(faces, np.int64))
        factor_bytes, factorised, solved = V * V * 8, time.perf_counter() - began, None
    return {"solver": solver, "mesh": mesh, "vertices": V, "factor_mb": round(factor_bytes / 2**20, 1),
            "factorise_s": round(factorised, 3),  # dense: the factorisation and one frame
            "transfer_ms_per_frame": None if solved is None else round(1000 * solved / FRAMES, 2),
            "peak_rss_gb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20, 3)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--one", nargs=2, metavar=("SOLVER", "MESH"), help=argparse.SUPPRESS)
    p.add_argument("--out", type=Path)
    args = p.parse_args()
    if args.one:
        print(json.dumps(one(*args.one)))
        return
    sys.path.insert(0, str(REPO / "tests"))
    rows = []
    for mesh in MESHES:
        for solver in ("dense", "sparse"):
            if solver == "dense" and mesh == "50k":
                continue
            result = subprocess.run([sys.executable, __file__, "--one", solver, mesh], capture_output=True, text=True,
                                    check=True, env={**os.environ, "PYTHONPATH": f"{REPO}:{REPO / 'tests'}"})
            rows.append(json.loads(result.stdout.strip().splitlines()[-1]))
            print(json.dumps(rows[-1]), flush=True)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
