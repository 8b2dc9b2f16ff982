"""Filmstrips of a checkpoint on the stream's stress splits: driver / target / result / ground truth.

    python bench/render_splits.py --checkpoint runs/default/best.pt --out docs/stress [--frames 12]

For each split, pair 0 of the test stream is drawn with a ``--frames``-long driving window (the same
families, bodies and orientations as the split's scored pairs, longer so that the motion shows)
and animated with the model's sliding window (aniformer.animate.animate_sequence), as jobs/animate.py
does. One PNG per split, plus the PMD of the shown clip for the model, copy-driver and the static target.
"""

from __future__ import annotations

import argparse
import functools
from pathlib import Path

import numpy as np
import torch

from aniformer.animate import animate_sequence
from aniformer.checkpoint import model_from_checkpoint
from aniformer.io.render import render_filmstrip
from aniformer.metrics import PMD_SCALE, pmd
from aniformer.synth.stream import TEST_SPLITS, StreamPairs


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", required=True)
    p.add_argument("--out", required=True)
    p.add_argument("--frames", type=int, default=12)
    p.add_argument("--splits", default=",".join(TEST_SPLITS))
    p.add_argument("--topology", help="default: the checkpoint's")
    p.add_argument("--pair", type=int, default=0)
    args = p.parse_args()
    model, state = model_from_checkpoint(args.checkpoint)
    model.eval()
    data = state["config"]["data"]
    stream = StreamPairs(args.topology or data["topology"], window=args.frames, seed=data.get("seed", 0))
    faces = stream.faces
    predict = functools.partial(model, faces=torch.from_numpy(faces))
    for split in args.splits.split(","):
        pair = stream.batch(split, 0, [args.pair])
        driving, target, truth = pair["driving"][0], pair["target"][0], pair["ground_truth"][0]
        result = animate_sequence(predict, driving, target, window=model.config.window,
                                  outputs=model.config.output_frames())
        scores = {name: pmd(torch.from_numpy(x), torch.from_numpy(truth)).item() * PMD_SCALE for name, x in
                  (("model", result), ("copy-driver", driving), ("static", np.repeat(target[None], len(truth), 0)))}
        title = f"{split}: PMD model {scores['model']:.1f}, copy-driver {scores['copy-driver']:.1f}, " \
                f"static target {scores['static']:.1f} (x1e-4)"
        rows = [("driver", driving, faces), ("target", np.repeat(target[None], len(truth), 0), faces),
                ("result", result, faces), ("ground truth", truth, faces)]
        path = render_filmstrip(rows, Path(args.out) / f"{split}.png", frames=6, title=title)
        print(f"{path}: {title}")


if __name__ == "__main__":
    main()
