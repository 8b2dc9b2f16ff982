"""PMD of jobs/animate.py's written frames on exported test clips, as a user runs it, per checkpoint.

    python bench/animate_quality.py --checkpoints pretrained skinned --splits heldout_actions locomotion --pairs 3 /tmp/q

For each split and pair, ``jobs/export_meshes.py --stream notoes_collapse3pc`` writes a test clip (fresh bodies,
``--frames`` frames) with its ground truth; ``jobs/animate.py --checkpoint C --center`` animates its target with
it; the OBJ frames it wrote are scored against the ground truth (PMD ×10⁻⁴, both bounding-box centred) beside
the deformation transfer alone (sliding its 3-frame window over the clip, as jobs/evaluate.py's row), copy-driver
and the static target. Prints one line per clip and a Markdown row per split: mean ± sd over pairs.
"""

from __future__ import annotations

import argparse
import functools
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

from aniformer.animate import animate_sequence, driving_files, load_driving
from aniformer.evaluate import TRANSFER, transfer_contender
from aniformer.geometry import center_bbox
from aniformer.io.mesh import load_mesh
from aniformer.metrics import PMD_SCALE, pmd

ROOT = Path(__file__).resolve().parents[1]
TOPOLOGY = "notoes_collapse3pc"


def _pmd(frames: np.ndarray, truth: np.ndarray) -> float:
    """PMD ×10⁻⁴ of two clips, each bounding-box centred as the stream's frames are."""
    return float(pmd(*(torch.from_numpy(center_bbox(np.asarray(x, np.float32))) for x in (frames, truth)))) * PMD_SCALE


def _job(*argv: str) -> None:
    run = subprocess.run([sys.executable, *argv], cwd=ROOT, capture_output=True, text=True)
    if run.returncode:
        raise SystemExit(f"{' '.join(argv)}: exit {run.returncode}\n{run.stderr[-2000:]}")


def score_clip(work: Path, split: str, pair: int, frames: int, checkpoints: list[str]) -> dict[str, float]:
    """PMD of each checkpoint's animation of one exported clip, and of the two trivial baselines."""
    clip = work / f"{split}-{pair}"
    if not (clip / "target.obj").is_file():
        _job("jobs/export_meshes.py", "--stream", TOPOLOGY, "--split", split, "--pair", str(pair), "--frames",
             str(frames), "--out", str(clip))
    truth, _ = load_driving(driving_files(clip / "ground_truth"))
    driving, _ = load_driving(driving_files(clip / "driving"))
    target, faces = load_mesh(clip / "target.obj")
    scores = {}
    for checkpoint in checkpoints:
        out = work / "anim" / checkpoint / f"{split}-{pair}"
        _job("jobs/animate.py", "--checkpoint", checkpoint, "--target", str(clip / "target.obj"), "--driving",
             str(clip / "driving"), "--out", str(out), "--center", "--overwrite", "--no-progress", "--no-glb",
             "--preview-frames", "0")
        scores[checkpoint] = _pmd(load_driving(driving_files(out / "frames"))[0], truth)
    transfer = transfer_contender(3)
    faces = torch.from_numpy(np.asarray(faces, np.int64))
    scores[TRANSFER] = _pmd(animate_sequence(functools.partial(transfer.predict, faces=faces), driving, target,
                                             window=transfer.window, outputs=transfer.frames), truth)
    scores["copy-driver"] = _pmd(driving, truth)
    scores["static target"] = _pmd(np.broadcast_to(target, truth.shape), truth)
    return scores


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoints", nargs="+", default=["pretrained", "skinned"])
    p.add_argument("--splits", nargs="+", default=["heldout_actions", "locomotion", "crouch", "extreme_bodies"])
    p.add_argument("--pairs", type=int, default=3)
    p.add_argument("--frames", type=int, default=30)
    p.add_argument("work", type=Path, help="work directory (exported clips and animate outputs, kept)")
    args = p.parse_args()
    for split in args.splits:
        rows = [score_clip(args.work, split, pair, args.frames, args.checkpoints) for pair in range(args.pairs)]
        for pair, row in enumerate(rows):
            print(f"{split} {pair}: " + ", ".join(f"{k} {v:.2f}" for k, v in row.items()), flush=True)
        columns = {k: np.array([row[k] for row in rows]) for k in rows[0]}
        trivial = np.minimum(columns["copy-driver"], columns["static target"]).mean()
        cells = [f"{v.mean():.1f} ± {v.std(ddof=1) if len(v) > 1 else 0:.1f}" for v in columns.values()]
        ratios = [f"{columns[c].mean() / trivial:.3f}" for c in args.checkpoints]
        print(f"| `{split}` | " + " | ".join(cells + ratios) + " |", flush=True)


if __name__ == "__main__":
    main()
