"""Render an animation result beside its inputs and ground truth (docs/animate_walk.png).

    python jobs/export_meshes.py --stream notoes_collapse3pc --split locomotion --out samples/walk
    python jobs/animate.py --checkpoint runs/default/best.pt --target samples/walk/target.obj \\
        --driving samples/walk/driving --out anim/walk
    python bench/render_animation.py samples/walk anim/walk docs/animate_walk.png

Rows: driver, target, result, ground truth at 8 evenly spaced frames, each mesh bounding-box
centred; prints the sequence's PMD (x1e-4) of result vs ground truth, against copying the driver
(driver vs ground truth, when they share a topology) and the static target, and the heights (z
extent, first frame) of target, driver and result.
"""

import json
import sys
from pathlib import Path

import numpy as np
import torch

from aniformer.animate import driving_files, load_driving
from aniformer.geometry import center_bbox
from aniformer.io.mesh import load_mesh
from aniformer.io.render import render_filmstrip
from aniformer.metrics import PMD_SCALE, pmd


def main(samples: str, animation: str, png: str) -> None:
    samples, animation = Path(samples), Path(animation)
    (driving, faces), (result, result_faces), (truth, truth_faces) = (
        load_driving(driving_files(str(d))) for d in (samples / "driving", animation / "frames", samples / "ground_truth"))
    target, target_faces = load_mesh(samples / "target.obj")
    shown = np.linspace(0, len(driving) - 1, 8).round().astype(int)
    rows = [("driver", driving[shown], faces), ("target", np.repeat(target[None], len(shown), 0), target_faces),
            ("result", result[shown], result_faces), ("ground truth", truth[shown], truth_faces)]
    info = json.loads((samples / "export.json").read_text())
    motion = info["motion"]["name"] if "motion" in info else f"{info['split']} pair {info['pair']} (stream)"
    render_filmstrip([(label, center_bbox(v), f) for label, v, f in rows], png, frames=len(shown),
                     title=f"{motion}: driver / target / result / ground truth (frames {', '.join(map(str, shown))})")
    def error(meshes: np.ndarray) -> float:
        return pmd(torch.from_numpy(center_bbox(meshes)), torch.from_numpy(center_bbox(truth))).item() * PMD_SCALE

    def height(vertices: np.ndarray) -> float:
        return float(np.ptp(vertices[..., 2]))

    copy = f"copy-driver {error(driving):.2f}" if driving.shape == truth.shape else "another topology than the driver's"
    print(f"{png}: PMD {error(result):.2f} x1e-4 over {len(driving)} frames ({copy}; static target "
          f"{error(np.broadcast_to(target, truth.shape)):.2f}); {len(target):,}-vertex target, "
          f"{driving.shape[1]:,}-vertex driver; "
          f"height target {height(target):.2f} m, driver {height(driving[0]):.2f} m, result {height(result[0]):.2f} m")


if __name__ == "__main__":
    main(*sys.argv[1:4])
