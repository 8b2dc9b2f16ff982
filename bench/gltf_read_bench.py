"""How fast a driving clip is read: the same frames as a folder of OBJs and as one animated GLB, side by side.

    python bench/gltf_read_bench.py --vertices 18000 --frames 300

Writes a random clip of ``--frames`` frames of ``--vertices`` vertices (and twice as many faces) as OBJ frames
(``aniformer.io.mesh.write_obj_frames``) and as animation.glb (``aniformer.io.glb.write_glb``), then times
``aniformer.animate.load_driving`` on each (best of ``--repeats``), and checks both give the same frames.
Prints one JSON line per input.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from aniformer.animate import driving_clip, driving_files, load_driving
from aniformer.io.glb import from_gltf_axes, write_glb
from aniformer.io.mesh import write_obj_frames


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--vertices", type=int, default=18_000)
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--repeats", type=int, default=3)
    args = p.parse_args()
    rng = np.random.default_rng(0)
    rest = rng.normal(size=(1, args.vertices, 3)) * 0.3
    frames = (rest + 0.01 * rng.normal(size=(args.frames, args.vertices, 3))).astype(np.float32)
    faces = rng.integers(0, args.vertices, (2 * args.vertices, 3))
    with tempfile.TemporaryDirectory() as scratch:
        scratch = Path(scratch)
        write_obj_frames(scratch / "frames", frames, faces)
        write_glb(scratch / "clip.glb", frames, faces)
        read = {}
        for name, source in (("OBJ folder", scratch / "frames"), ("animated GLB", scratch / "clip.glb")):
            files = driving_files(source)
            seconds = []
            for _ in range(args.repeats):
                began = time.perf_counter()
                read[name], _ = load_driving(files, clip=driving_clip(files))
                seconds.append(time.perf_counter() - began)
            print(json.dumps({"input": name, "vertices": args.vertices, "frames": args.frames,
                              "seconds": round(min(seconds), 2), "frames_per_s": round(args.frames / min(seconds), 1)}))
        # the GLB is read in glTF's axes (y up); turned back, both are the same frames
        assert np.abs(from_gltf_axes(read["animated GLB"]) - read["OBJ folder"]).max() < 1e-5


if __name__ == "__main__":
    main()
