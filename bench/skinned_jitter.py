"""Jitter of the skinned transfer on whole test clips, beside the shipped model and the deformation transfer.

    python bench/skinned_jitter.py --splits heldout_actions locomotion crouch extreme_bodies --clips 6

The clips are ``jobs/evaluate.py --clip-frames 16``'s (the stream's test pairs, seed 0). The model and the
transfer slide their windows over each clip (``aniformer.animate.animate_sequence``); the skinned transfer fits
every frame of it at once, as ``jobs/animate.py --checkpoint skinned`` does. Prints per split the acceleration
error (mm/frame², ``aniformer.evaluate.acceleration_error``) mean ± sd over clips, and the skinned transfer's PMD.
jobs/evaluate.py leaves the skinned transfer out of its acceleration table: ~15 s per clip on 2 cores.
"""

from __future__ import annotations

import argparse
import functools
import time

import numpy as np
import torch

from aniformer.animate import animate_sequence
from aniformer.checkpoint import model_from_checkpoint, resolve_pretrained
from aniformer.evaluate import acceleration_error, model_contender, transfer_contender
from aniformer.metrics import PMD_SCALE, pmd_per_frame
from aniformer.skinned_transfer import skinned_transfer
from aniformer.synth.stream import StreamPairs


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--splits", nargs="+", default=["heldout_actions", "locomotion", "crouch", "extreme_bodies"])
    p.add_argument("--clips", type=int, default=6)
    p.add_argument("--frames", type=int, default=16)
    args = p.parse_args()
    model, _ = model_from_checkpoint(resolve_pretrained("pretrained"))
    stream = StreamPairs("notoes_collapse3pc", window=args.frames, center="mesh")
    sliding = {"shipped model": model_contender("model", model), "deformation transfer": transfer_contender(3)}
    for split in args.splits:
        began = time.perf_counter()
        batch = stream.batch(split, 0, np.arange(args.clips))
        jitter, pmd = {name: [] for name in [*sliding, "skinned transfer"]}, []
        for i in range(args.clips):
            faces, truth = torch.from_numpy(batch["target_faces"][i]), torch.from_numpy(batch["ground_truth"][i])
            driving, target = batch["driving"][i], batch["target"][i]
            for name, contender in sliding.items():
                frames = animate_sequence(functools.partial(contender.predict, faces=faces), driving, target,
                                          window=contender.window, outputs=contender.frames)
                jitter[name].append(float(acceleration_error(torch.from_numpy(frames), truth)) * 1000)
            frames = skinned_transfer(torch.from_numpy(driving[None]), torch.from_numpy(target[None]), faces)[0]
            jitter["skinned transfer"].append(float(acceleration_error(frames, truth)) * 1000)
            pmd.append(float(pmd_per_frame(frames, truth).mean()) * PMD_SCALE)
        cells = ", ".join(f"{name} {np.mean(v):.2f} ± {np.std(v, ddof=1):.2f}" for name, v in jitter.items())
        print(f"{split}: acceleration error {cells}; skinned PMD {np.mean(pmd):.2f} "
              f"({time.perf_counter() - began:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
