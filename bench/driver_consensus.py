"""Calibrate the agreement of a foreign driver's fits on different frames of its clip (validation only).

    python bench/driver_consensus.py --pairs 16 --out /tmp/consensus.json

Per ``foreign_driver`` pair of split ``seen``: the driver's mesh fitted on frames 0, the middle and the last
(``aniformer.correspondence.register_clip``'s candidates), each fit's registration checks, each fit's error
(the clip read on the template against the true driver on it, each frame's mean removed) and every two fits'
disagreement, both as ``aniformer.correspondence.part_rms_distance`` in body heights. A limit on the
disagreement must sit between two good fits and a good and a bad one.
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import numpy as np

from aniformer.checkpoint import PRETRAINED, load_checkpoint
from aniformer.correspondence import Correspondence, part_rms_distance
from aniformer.synth.stream import StreamPairs
from aniformer.synth.variants import variant_pairs
from aniformer.trust import registration_checks, stretch_check


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pairs", type=int, default=16)
    p.add_argument("--first", type=int, default=0)
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args()
    state = load_checkpoint(PRETRAINED)
    topology = state["config"]["data"]["topology"]
    stream = StreamPairs(topology, window=state["config"]["model"].get("window", 3), seed=0)
    rows = []
    for index in range(args.first, args.first + args.pairs):
        case = variant_pairs(stream, "seen", 0, [index], ["foreign_driver"])[0]["foreign_driver"]
        frames = case["driving"]
        truth = case["copy_driver"] - case["copy_driver"].mean(1, keepdims=True)
        reads = {}
        for k in np.unique(np.linspace(0, len(frames) - 1, 3).round().astype(int)):
            fit = Correspondence(frames[k], case["driving_faces"], topology)
            read = fit.to_template(frames)
            checks = [*registration_checks(fit, "driver"), stretch_check(read, fit.template, fit.template_faces)]
            reads[int(k)] = read, fit.fitted.height
            error = part_rms_distance(read - read.mean(1, keepdims=True), truth, topology) / fit.fitted.height
            rows.append({"pair": index, "frame": int(k), "error": error,
                         "badness": max(c.value / c.limit for c in checks), "failed": [c.name for c in checks if not c.ok]})
        for a, b in itertools.combinations(reads, 2):
            disagreement = part_rms_distance(reads[a][0], reads[b][0], topology) / reads[a][1]
            rows.append({"pair": index, "frames": [a, b], "disagreement": disagreement})
        print(json.dumps(rows[-6:]), flush=True)
    args.out.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
