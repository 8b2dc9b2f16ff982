"""Calibrate the self-check (aniformer/trust.py) on good and broken registrations of validation pairs.

    python bench/trust_calibration.py --pairs 12 --out bench/results/trust.json

Validation split ``seen`` only (the test splits stay held out). Per pair, the target as users bring
it (``aniformer.synth.variants``: remeshed, posed, rotated), registered and animated by the shipped
model through the registration; then the same registration deliberately broken (heading, tilt,
swapped arm). Each case's checks and its PMD against the ground truth and the better trivial baseline are written;
a check's limit must sit between the good cases and the broken ones. The broken ones are
``aniformer.trust.injected_failures``.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

from aniformer.checkpoint import PRETRAINED, model_from_checkpoint
from aniformer.correspondence import Correspondence
from aniformer.evaluate import model_contender
from aniformer.geometry import center_bbox
from aniformer.metrics import PMD_SCALE
from aniformer.synth.stream import StreamPairs
from aniformer.synth.variants import variant_pairs
from aniformer.trust import animation_trust, injected_failures

VARIANTS = ("remeshed", "posed", "rotated")


def _score(fit: Correspondence, predict, driving: np.ndarray, case: dict, frames: slice) -> dict:
    faces = torch.from_numpy(fit.template_faces)
    posed = predict(torch.from_numpy(driving[None]), torch.from_numpy(fit.unposed_template[None]), faces)[0].numpy()
    result = fit.from_template(posed)
    trust = animation_trust(result, fit.vertices, fit.faces, fit)
    truth = case["ground_truth"][frames]
    pmd = float(np.square(center_bbox(result) - truth).sum(-1).mean() * PMD_SCALE)
    copy = float(np.square(case["copy_driver"][frames] - truth).sum(-1).mean() * PMD_SCALE)
    static = float(np.square(case["target"][None] - truth).sum(-1).mean() * PMD_SCALE)
    return {"pmd": pmd, "ratio": pmd / min(copy, static), "trust": trust.to_dict()}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pairs", type=int, default=12)
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args()
    model, state = model_from_checkpoint(PRETRAINED)
    predict = model_contender("model", model).predict
    stream = StreamPairs(state["config"]["data"]["topology"], window=model.config.window, seed=0)
    frames = model.config.output_frames()
    rows = []
    for index in range(args.pairs):
        pair = variant_pairs(stream, "seen", 0, [index], VARIANTS)[0]
        for variant in VARIANTS:
            case = pair[variant]
            began = time.perf_counter()
            fit = Correspondence(case["target"], case["faces"], stream.topology)
            seconds = time.perf_counter() - began
            cases = {"good": fit, **{name: Correspondence(fit.vertices, fit.faces, fit.topology, fitted=broken)
                                     for name, broken in injected_failures(fit).items()}}
            for kind, c in cases.items():
                row = {"pair": index, "variant": variant, "kind": kind, "seconds": round(seconds, 1),
                       **_score(c, predict, pair["driving"], case, frames)}
                rows.append(row)
                checks = " ".join(f"{c['name']} {c['value']:.3f}" for c in row["trust"]["checks"])
                print(f"{index} {variant:9s} {kind:12s} ratio {row['ratio']:7.3f} pmd {row['pmd']:8.1f} "
                      f"{'ok ' if row['trust']['ok'] else 'REFUSED'} {checks}", flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(rows, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
