"""Characters as users bring them, animated by a foreign driver through jobs/animate.py, as filmstrips.

    python bench/character_filmstrips.py --pair 2 --out bench/results/characters docs/characters
    python bench/character_filmstrips.py --pair 2 --checkpoint skinned bench/results/skinned docs/characters/skinned

For one test pair (split ``characters``), the target as a y-up GLB, in a random pose and lying
(``aniformer.synth.variants``), each driven by the same 24-frame clip of a decimated, shuffled body
that starts mid-motion (``foreign_driver``). Each runs ``jobs/animate.py`` as a user would (its
``--checkpoint``, the shipped model by default; ``--up auto``); a refused result is run again with
``--force`` to look at what the self-check kept from being written. Rows of each PNG: driver, target,
result, ground truth; it prints each run's exit status, self-check and PMD beside copy-driver and the
static target.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import trimesh

from aniformer.animate import driving_files, load_driving
from aniformer.geometry import center_bbox, from_z_up, to_z_up
from aniformer.io.mesh import write_obj
from aniformer.io.render import render_filmstrip
from aniformer.metrics import PMD_SCALE
from aniformer.synth.stream import StreamPairs
from aniformer.synth.variants import DRIVER_FRAMES, variant_pairs

ROOT = Path(__file__).resolve().parents[1]
TARGETS = ("glb", "posed", "lying")


def _pmd(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.square(center_bbox(a) - center_bbox(b)).sum(-1).mean() * PMD_SCALE)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pair", type=int, default=2)
    p.add_argument("--checkpoint", default="pretrained", help="jobs/animate.py's --checkpoint (default pretrained)")
    p.add_argument("out", type=Path, help="work directory (inputs and animate outputs)")
    p.add_argument("png", type=Path, help="directory of the filmstrips")
    args = p.parse_args()
    stream = StreamPairs("notoes_collapse3pc", window=DRIVER_FRAMES, seed=0)
    pair = variant_pairs(stream, "characters", 0, [args.pair], [*TARGETS, "foreign_driver"])[0]
    driver = pair["foreign_driver"]
    clip = args.out / "driving"
    clip.mkdir(parents=True, exist_ok=True)
    for k, frame in enumerate(driver["driving"]):
        write_obj(clip / f"frame_{k:04d}.obj", frame, driver["driving_faces"])
    args.png.mkdir(parents=True, exist_ok=True)
    for variant in TARGETS:
        case = pair[variant]
        if variant == "glb":
            target_file = args.out / "glb_character.glb"
            trimesh.Trimesh(from_z_up(case["target"], "y"), case["faces"], process=False).export(target_file)
        else:
            target_file = args.out / f"{variant}_character.obj"
            write_obj(target_file, case["target"], case["faces"])
        for force in (False, True):
            out = args.out / f"anim_{variant}{'_forced' if force else ''}"
            argv = [sys.executable, "jobs/animate.py", "--checkpoint", args.checkpoint, "--target", str(target_file),
                    "--driving", str(clip), "--out", str(out), "--overwrite", "--no-progress", "--preview-frames", "0",
                    "--no-glb", *(["--force"] if force else [])]
            run = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True)
            lines = [line for line in (run.stdout + run.stderr).splitlines() if "self-check" in line or "registered" in line]
            print(f"{variant}{' --force' if force else ''}: exit {run.returncode}; " + " | ".join(lines), flush=True)
            if run.returncode == 0:
                break
        result, _ = load_driving(driving_files(out / "frames"))
        up = json.loads((out / "animation.json").read_text())["up"]["target"]["axis"]
        result = to_z_up(result, up)
        truth = case["ground_truth"]
        scores = {"result": _pmd(result, truth), "copy-driver": _pmd(case["copy_driver"], truth),
                  "static target": _pmd(np.broadcast_to(case["target"], truth.shape), truth)}
        print("  PMD x1e-4: " + ", ".join(f"{k} {v:.1f}" for k, v in scores.items()), flush=True)
        shown = np.linspace(0, DRIVER_FRAMES - 1, 8).round().astype(int)
        rows = [("driver", driver["driving"][shown], driver["driving_faces"]),
                ("target", np.repeat(case["target"][None], len(shown), 0), case["faces"]),
                ("result" + (" (--force)" if force else ""), result[shown], case["faces"]),
                ("ground truth", truth[shown], case["faces"])]
        render_filmstrip([(label, center_bbox(v), f) for label, v, f in rows], args.png / f"{variant}.png",
                         frames=len(shown), title=f"{variant} character, foreign driver starting mid-motion: "
                                                  f"PMD {scores['result']:.1f} (copy-driver {scores['copy-driver']:.1f}, "
                                                  f"static {scores['static target']:.1f})")
        print(f"  wrote {args.png / f'{variant}.png'}")


if __name__ == "__main__":
    main()
