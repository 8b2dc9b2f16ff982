"""Throughput of BodyModel.pose on CPU: meshes per second for batches of procedural poses.

Two cases per batch size: every mesh a different identity, and clips (30 frames sharing one
identity, as the data pipeline poses them; pose() computes each distinct rest shape once).
Reports the best of --repeats runs (the machine may be shared). Run from the repository root:
python bench/synth_bench.py [--batches 30 120 480] [--repeats 5]
"""

import argparse
import time

import numpy as np
import torch

from aniformer.synth.bodies import BodyModel, sample_identities
from aniformer.synth.motions import ACTIONS, sample_motion

CLIP = 30


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--topologies", nargs="+", default=["notoes_collapse10pc", "notoes"])
    parser.add_argument("--batches", nargs="+", type=int, default=[1, 30, 120, 480])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads")
    print("| topology | vertices | batch | identities | ms / batch (best) | meshes / s |")
    print("|---|---|---|---|---|---|")
    for topology in args.topologies:
        body = BodyModel(topology)
        for batch in args.batches:
            clips = max(1, batch // CLIP)
            motions = [sample_motion(ACTIONS[i % len(ACTIONS)], i, body.bone_labels, CLIP) for i in range(clips)]
            rotvecs = np.concatenate([m.rotvecs for m in motions])[:batch]
            translation = np.concatenate([m.translation for m in motions])[:batch]
            distinct = sample_identities(batch, seed=0)
            shared = np.repeat(sample_identities(clips, seed=0), CLIP, axis=0)[:batch]
            for name, identities in (("distinct", distinct), (f"1 per {CLIP} frames", shared)):
                if batch == 1 and name != "distinct":
                    continue
                body.pose(identities, rotvecs, translation)  # warm-up
                times = []
                for _ in range(args.repeats):
                    start = time.perf_counter()
                    body.pose(identities, rotvecs, translation)
                    times.append(time.perf_counter() - start)
                best = min(times)
                row = [topology, body.num_vertices, batch, name, f"{1000 * best:.1f}", f"{batch / best:.0f}"]
                print("| " + " | ".join(map(str, row)) + " |", flush=True)


if __name__ == "__main__":
    main()
