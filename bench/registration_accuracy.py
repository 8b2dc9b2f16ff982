"""How close the registration lands to the true body: template error of posed and turned characters.

    python bench/registration_accuracy.py --pairs 8 --out bench/results/registration.json

Validation split ``seen`` only (the test splits stay held out). Per pair, the target body as
``aniformer.synth.variants`` makes the ``posed`` character (Anny's full body decimated, in a random
pose of the split's families), optionally turned by a uniformly random rotation (``--turned``). The
true template is the same body and pose at the model's topology, so the error of the fit is the mean
distance of the fitted template's vertices to their true places, in cm (and the worst vertex's); also
the fit's time and the self-check's registration checks (``aniformer.trust.registration_checks``).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from aniformer.correspondence import Correspondence
from aniformer.synth.stream import StreamPairs, _generator
from aniformer.synth.variants import posed_character, random_rotation
from aniformer.trust import registration_checks

SPLIT = "seen"
TOPOLOGY = "notoes_collapse3pc"  # the shipped model's


def posed_case(stream: StreamPairs, index: int, turned: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(the character's vertices, faces, the true template ``(V_a, 3)`` in the character's coordinates)."""
    target, faces, truth = posed_character(stream, SPLIT, 0, index, TOPOLOGY)
    if turned:
        turn = random_rotation(_generator(0, "bench-turn", SPLIT, 0, index)).astype(np.float32)
        target, truth = target @ turn.T, truth @ turn.T
    return target, faces, truth


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pairs", type=int, default=8)
    p.add_argument("--first", type=int, default=0)
    p.add_argument("--turned", action="store_true")
    p.add_argument("--steps", type=lambda s: tuple(int(n) for n in s.split(",")), default=None, metavar="C,R,O",
                   help="the fit's steps: coarse, refinement, offsets (default: fit_template's)")
    p.add_argument("--seed", type=int, default=0, help="the fit's sampling seed (fit_template's ``seed``)")
    p.add_argument("--only", type=lambda s: [int(n) for n in s.split(",")], default=None, metavar="I,J",
                   help="of the pairs, only these indices")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args()
    stream = StreamPairs(TOPOLOGY, window=3, seed=0)
    rows = []
    for index in args.only or range(args.first, args.first + args.pairs):
        target, faces, truth = posed_case(stream, index, args.turned)
        start = time.perf_counter()
        fit = Correspondence(target, faces, TOPOLOGY, seed=args.seed, **({"steps": args.steps} if args.steps else {}))
        seconds = time.perf_counter() - start
        error = 100 * float(np.linalg.norm(fit.fitted.vertices - truth, axis=1).mean())
        part = np.linalg.norm(fit.fitted.vertices - truth, axis=1)
        checks = {c.name: round(c.value, 4) for c in registration_checks(fit)}
        rows.append({"index": index, "error_cm": round(error, 2), "worst_vertex_cm": round(100 * float(part.max()), 1),
                     "rms_m": round(fit.rms, 4), "seconds": round(seconds, 1), "checks": checks})
        print(json.dumps(rows[-1]), flush=True)
    errors = np.array([r["error_cm"] for r in rows])
    summary = {"mean_cm": round(float(errors.mean()), 2), "median_cm": round(float(np.median(errors)), 2),
               "over_5cm": int((errors > 5).sum()), "pairs": len(rows), "turned": args.turned,
               "steps": args.steps, "seed": args.seed}
    print(json.dumps(summary))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"summary": summary, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
