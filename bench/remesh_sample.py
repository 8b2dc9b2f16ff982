"""A remeshed copy of an exported sample: its target decimated to a topology of its own, with the
ground truth followed onto the new vertices (what docs/results.md's `remeshed` targets are).

    python jobs/export_meshes.py --stream notoes --split characters --pair 3 --out samples/full
    python jobs/export_meshes.py --stream notoes_collapse3pc --split characters --pair 3 --out samples/drive
    python bench/remesh_sample.py samples/full samples/remeshed samples/drive/driving
    python jobs/animate.py --target samples/remeshed/target.obj --driving samples/remeshed/driving --out anim/remeshed
    python bench/render_animation.py samples/remeshed anim/remeshed docs/animate_remeshed.png

The driving frames are copied from the third argument (the same pair at another topology: a pair's
bodies and motion do not depend on the topology), else from the sample.
"""

import shutil
import sys
from pathlib import Path

from aniformer.animate import driving_files, load_driving
from aniformer.io.mesh import load_mesh, write_obj
from aniformer.surface import closest_points
from aniformer.synth.variants import remesh


def main(samples: str, out: str, driving: str | None = None) -> None:
    samples, out = Path(samples), Path(out)
    target, faces = load_mesh(samples / "target.obj")
    truth, truth_faces = load_driving(driving_files(str(samples / "ground_truth")))
    vertices, new_faces = remesh(target, faces)
    on_body = closest_points(vertices, target, faces)
    (out / "ground_truth").mkdir(parents=True)
    shutil.copytree(driving or samples / "driving", out / "driving")
    shutil.copy(samples / "export.json", out / "export.json")
    write_obj(out / "target.obj", vertices, new_faces)
    for k, frame in enumerate(on_body.on(truth, truth_faces)):
        write_obj(out / "ground_truth" / f"frame_{k:04d}.obj", frame, new_faces)
    print(f"{out}: {len(target):,}-vertex target remeshed to {len(vertices):,} vertices, {len(new_faces):,} faces")


if __name__ == "__main__":
    main(*sys.argv[1:4])
