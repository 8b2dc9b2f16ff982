"""How faithful ``jobs/animate.py --rig`` is: the rig's PMD to the animated frames and to the ground truth,
against the frames' own PMD to the ground truth, and rigged.glb's size against animation.glb's, with the
shipped model on 20-frame clips of the stream's test splits.

Run from the repository root (~5 min on 2 cores):

    python bench/rig_quality.py --pairs 2 --out bench/results/rig_quality.json

Targets: ``same`` (the pair's target on the model's Anny topology: no registration) and ``remeshed``
(Anny's full body decimated to a mesh of its own: registered), as ``aniformer.synth.variants`` makes them.
Every mesh is bounding-box centred before scoring, as evaluate does; PMD is x1e-4 m^2.
"""

from __future__ import annotations

import argparse
import copy
import json
import tempfile
from pathlib import Path

import numpy as np
import torch

CLIP_FRAMES = 20  # the longest window the motion library gives at its largest stride (60 frames, stride 3)
VARIANTS = ("same", "remeshed")


def main() -> None:
    from aniformer.animate import animate_sequence
    from aniformer.checkpoint import PRETRAINED, model_from_checkpoint
    from aniformer.correspondence import Correspondence
    from aniformer.evaluate import model_contender
    from aniformer.geometry import center_bbox
    from aniformer.io.glb import write_glb
    from aniformer.io.rigged_glb import write_rigged_glb
    from aniformer.metrics import PMD_SCALE, pmd_per_frame
    from aniformer.rig import build_rig, skin
    from aniformer.rig_motion import fit_rig
    from aniformer.synth.stream import TEST_SPLITS, StreamPairs
    from aniformer.synth.variants import variant_pairs
    from aniformer.transfer import deformation_transfer

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--pairs", type=int, default=2, help="pairs per test split")
    p.add_argument("--out", type=Path)
    args = p.parse_args()
    model, state = model_from_checkpoint(PRETRAINED)
    topology = state["config"]["data"]["topology"]
    predict = model_contender("model", model).predict
    stream = StreamPairs(topology, window=model.config.window, seed=0)
    clip = copy.copy(stream)
    clip.window = CLIP_FRAMES  # the same pairs, a longer driving clip
    faces = torch.from_numpy(np.asarray(stream.faces, np.int64))

    def score(a: np.ndarray, b: np.ndarray) -> float:
        return float(pmd_per_frame(torch.from_numpy(center_bbox(a)), torch.from_numpy(center_bbox(b))).mean()) * PMD_SCALE

    rows = []
    with tempfile.TemporaryDirectory(prefix="aniformer-rig-") as scratch:
        for split in TEST_SPLITS:
            for pair in variant_pairs(clip, split, 0, range(args.pairs), VARIANTS):
                for variant in VARIANTS:
                    case = pair[variant]
                    registered = not np.array_equal(case["faces"], stream.faces)
                    fit = Correspondence(case["target"], case["faces"], topology) if registered else None
                    template = fit.template if registered else case["target"]
                    posed = animate_sequence(lambda d, t: predict(d, t, faces), pair["driving"], template,
                                             window=model.config.window, outputs=model.config.output_frames())
                    frames = center_bbox(fit.from_template(posed) if registered else posed)
                    moved = deformation_transfer(torch.from_numpy(pair["driving"][None]), torch.from_numpy(template[None]),
                                                 faces)[0].numpy()
                    transfer_alone = center_bbox(fit.from_template(moved) if registered else moved)
                    source = (fit.template, topology, fit.mesh_on_template) if registered else (case["target"], topology, None)
                    rig, motion = fit_rig(build_rig(case["target"], *source), case["target"], frames)
                    skinned = skin(rig, case["target"], torch.from_numpy(motion.world)).numpy()
                    animation_glb = write_glb(Path(scratch) / "animation.glb", frames, case["faces"])
                    rigged_glb = write_rigged_glb(Path(scratch) / "rigged.glb", case["target"], case["faces"], rig, motion)
                    rows.append({"split": split, "variant": variant, "vertices": len(case["target"]),
                                 "joints": len(rig.names), "frames_to_truth": score(frames, case["ground_truth"]),
                                 "rig_to_frames": score(skinned, frames), "rig_to_truth": score(skinned, case["ground_truth"]),
                                 "transfer_alone": score(transfer_alone, case["ground_truth"]),
                                 "copy_driver": score(case["copy_driver"], case["ground_truth"]),
                                 "static_target": score(np.broadcast_to(case["target"], frames.shape), case["ground_truth"]),
                                 "size_ratio": rigged_glb.stat().st_size / animation_glb.stat().st_size})
                    print(json.dumps(rows[-1]), flush=True)
    for variant in VARIANTS:
        mine = [r for r in rows if r["variant"] == variant]
        summary = {key: f"{np.mean([r[key] for r in mine]):.2f} ± {np.std([r[key] for r in mine]):.2f}"
                   for key in ("frames_to_truth", "rig_to_frames", "rig_to_truth", "transfer_alone", "copy_driver",
                               "static_target", "size_ratio")}
        ratio = [r["rig_to_frames"] / r["frames_to_truth"] for r in mine]
        print(variant, len(mine), "pairs:", summary, f"rig_to_frames / frames_to_truth {np.mean(ratio):.3f} "
              f"(max {np.max(ratio):.3f})")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
