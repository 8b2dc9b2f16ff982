"""Stream pairs with targets the model's topology does not have, and their ground truth (no Ray).

A user's character is not Anny's mesh at the training topology. The same pair (bodies, driving
window, target pose) is made with the target as:

- ``same``: the training topology, as trained;
- ``topology``: another Anny topology (``OTHER_TOPOLOGY``: another vertex count and connectivity);
- ``shuffled``: the training topology in a random vertex order (faces remapped);
- ``remeshed``: Anny's full-resolution body decimated by quadric edge collapse to
  ``REMESH_FACES`` triangles (new vertices, no vertex shared with any Anny topology).

Each carries the ground truth on the target's own vertices (for ``remeshed``: every vertex's
closest point on the full-resolution target, followed into the ground-truth poses) and the
copy-driver baseline carried the same way (the driver's body at the target's vertices).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import trimesh

from aniformer.mesh import center_bbox, shuffle_vertices
from aniformer.synth.stream import StreamPairs, _body_model, _generator, pose_pairs

VARIANTS: dict[str, str] = {
    "same": "the training topology",
    "topology": "another Anny topology",
    "shuffled": "the training topology, vertices shuffled",
    "remeshed": "Anny's full body decimated to another mesh",
}
OTHER_TOPOLOGY = {"notoes_collapse3pc": "notoes_collapse10pc"}  # else notoes_collapse3pc
FULL_TOPOLOGY = "notoes"
REMESH_FACES = 3000


def remesh(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A quadric decimation of a mesh: (vertices, faces) of its own topology."""
    simplified = trimesh.Trimesh(vertices, faces, process=False).simplify_quadric_decimation(face_count=REMESH_FACES)
    return np.asarray(simplified.vertices, np.float32), np.asarray(simplified.faces, np.int64)


def variant_pairs(stream: StreamPairs, split: str, epoch: int, indices: Sequence[int],
                  variants: Sequence[str]) -> list[dict]:
    """Per pair: ``driving (T, V, 3)`` at the stream's topology and, per variant, a dict of
    ``target (N, 3)``, ``faces (F, 3)``, ``ground_truth (T, N, 3)`` and ``copy_driver (T, N, 3)``;
    all bounding-box centred per mesh."""
    from aniformer.registration import closest_points

    draws = stream.draws(split, epoch, indices)
    topologies = {"same": stream.topology, "shuffled": stream.topology,
                  "topology": OTHER_TOPOLOGY.get(stream.topology, "notoes_collapse3pc"), "remeshed": FULL_TOPOLOGY}
    meshes = {t: pose_pairs(_body_model(t), draws) for t in {topologies[v] for v in variants} | {stream.topology}}
    driving = center_bbox(meshes[stream.topology][0])
    pairs = []
    for b, index in enumerate(indices):
        pair = {"driving": driving[b]}
        for variant in variants:
            drive, truth, target = (m[b] for m in meshes[topologies[variant]])
            target, faces = target[0], _body_model(topologies[variant]).faces
            if variant == "shuffled":
                perm = _generator(stream.seed, "shuffle", split, int(epoch), int(index)).permutation(len(target))
                _, faces = shuffle_vertices(target, faces, perm)
                target, drive, truth = (x[..., perm, :] for x in (target, drive, truth))
            elif variant == "remeshed":
                remeshed, remeshed_faces = remesh(target, faces)
                on_body = closest_points(remeshed, target, faces)
                drive, truth = (on_body.on(x, faces) for x in (drive, truth))
                target, faces = remeshed, remeshed_faces
            pair[variant] = {"target": center_bbox(target), "faces": faces, "ground_truth": center_bbox(truth),
                             "copy_driver": center_bbox(drive)}
        pairs.append(pair)
    return pairs
