"""Seconds of the per-mesh graph steps a registration and the self-check run on a target, by checkout.

    python bench/mesh_graph_bench.py --mesh /tmp/bi/target_72k.obj --checkout before=/tmp/base --checkout after=.

The steps are the ones whose cost grows with the target's vertex count, outside the fit's optimisation:
``mesh_edges``, the edge graph with split vertices joined (``surface._edge_graph``), ``surface_parts``,
``geodesic_frame`` and ``extremities`` (``detect_up``'s cue). Each step is timed on its first call in a
fresh process of its checkout, as a job calls it once per mesh; the median over ``--repeats`` processes is
reported, and each step's output is hashed so that the checkouts can be seen to agree.
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

PROBE = r"""
import hashlib, json, sys, time
import numpy as np, trimesh
from aniformer.surface import _edge_graph, extremities, geodesic_frame, surface_parts
from aniformer.transfer import mesh_edges

mesh = trimesh.load(sys.argv[1], process=False)
vertices, faces = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
steps = {
    "mesh_edges": lambda: mesh_edges(faces, len(vertices)),
    "edge graph": lambda: _edge_graph(vertices, faces),
    "surface_parts": lambda: surface_parts(vertices, faces),
    "geodesic_frame": lambda: geodesic_frame(vertices, faces),
    "extremities": lambda: extremities(vertices, faces),
}

def digest(value):
    if hasattr(value, "tocoo"):
        value = value.tocoo()
        value = (value.row, value.col, value.data)
    if hasattr(value, "coordinates"):
        value = (value.coordinates, *value.regions)
    parts = value if isinstance(value, (tuple, list)) else (value,)
    return hashlib.sha256(b"".join(np.ascontiguousarray(p).tobytes() for p in parts)).hexdigest()[:12]

began = time.perf_counter()
out = steps[sys.argv[2]]()
print(json.dumps({"vertices": len(vertices), "seconds": time.perf_counter() - began, "output": digest(out)}))
"""
STEPS = ("mesh_edges", "edge graph", "surface_parts", "geodesic_frame", "extremities")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--mesh", type=Path, required=True, help="an OBJ target (bench/animate_bench.py --inputs makes them)")
    p.add_argument("--checkout", action="append", required=True, help="NAME=PATH of a repository checkout (repeat)")
    p.add_argument("--repeats", type=int, default=3, help="processes per step and checkout")
    args = p.parse_args()
    checkouts = [c.split("=", 1) for c in args.checkout]
    runs = {(name, step): [] for name, _ in checkouts for step in STEPS}
    for _ in range(args.repeats):  # checkouts alternate, so that a change in the machine's load hits both
        for (name, path), step in itertools.product(checkouts, STEPS):
            env = {**os.environ, "PYTHONPATH": str(Path(path).resolve())}
            result = subprocess.run([sys.executable, "-c", PROBE, str(args.mesh.resolve()), step], env=env, cwd=path,
                                    capture_output=True, text=True, check=True)  # cwd: -c puts it first on sys.path
            runs[name, step].append(json.loads(result.stdout.splitlines()[-1]))
    for name, _ in checkouts:
        steps = {step: {"seconds": round(statistics.median(r["seconds"] for r in runs[name, step]), 4),
                        "output": sorted({r["output"] for r in runs[name, step]})} for step in STEPS}
        print(json.dumps({"checkout": name, "vertices": runs[name, STEPS[0]][0]["vertices"], "steps": steps}))


if __name__ == "__main__":
    main()
