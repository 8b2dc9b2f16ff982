"""Stream pairs with targets and drivers the model's topology does not have, and their ground truth (no Ray).

A user's character is not Anny's mesh at the training topology. The same pair (bodies, driving
window, target pose) is made with the target as:

- ``same``: the training topology, as trained;
- ``topology``: another Anny topology (``OTHER_TOPOLOGY``: another vertex count and connectivity);
- ``shuffled``: the training topology in a random vertex order (faces remapped);
- ``remeshed``: Anny's full-resolution body decimated by quadric edge collapse to
  ``REMESH_FACES`` triangles (new vertices, no vertex shared with any Anny topology).

Characters as users bring them start from Anny's full-resolution target body at rest, decimated
the same way (``CARRIED``: its vertices attached to the body, ``AttachedPoints``, and carried into
any pose):

- ``posed``: in a pose of the split's families, upright, drawn at a seed of its own, instead of
  the split's target pose;
- ``rotated``: ``posed`` turned by a uniformly random rotation;
- ``lying``: turned 90 degrees about a random horizontal axis after a random heading;
- ``glb``: written to a GLB file in glTF's y-up axes with trimesh, read back with
  ``aniformer.io.mesh.load_mesh`` and turned z-up again;
- ``parts``: with an artist's separate parts: an eyeball in each eye socket (at Anny's ``eye.L``
  and ``eye.R`` bone heads) and a teeth box in the mouth cavity;
- ``props``: holding a sword, a ``PROP_LENGTH`` stick pointing forward out of the right palm, a separate
  part carried rigidly by the hand (``AttachedPoints.rigid``).

and two more:

- ``dense``: Anny's full-resolution body subdivided past ``DENSE_VERTICES`` vertices (edge
  midpoints), its vertices shuffled;
- ``foreign_driver``: the training topology driven by a clip of another topology: the driver's
  full-resolution body at rest decimated, carried through a ``DRIVER_FRAMES``-frame window of the
  split (which starts wherever the motion is, not at rest), its vertices shuffled.

Each carries the ground truth on the target's own vertices: the target identity in the driving
poses, in the driver's axes (a turned target is to move as the driver does), through the same
carry as the target (for ``remeshed``: every vertex's closest point on the full-resolution target,
followed into the ground-truth poses), and the copy-driver baseline carried the same way (the
driver's body at the target's vertices).
"""

from __future__ import annotations

import copy
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.spatial.transform
import torch
import trimesh

from aniformer.geometry import center_bbox, from_z_up, shuffle_vertices, to_z_up
from aniformer.io.mesh import load_mesh
from aniformer.surface import SurfacePoints, closest_points
from aniformer.synth.poses import sample_windows
from aniformer.synth.stream import StreamPairs, _body_model, _choose, _generator, pose_pairs

VARIANTS: dict[str, str] = {
    "same": "the training topology",
    "topology": "another Anny topology",
    "shuffled": "the training topology, vertices shuffled",
    "remeshed": "Anny's full body decimated to another mesh",
    "posed": "Anny's full body decimated, in a random upright pose of the split's families",
    "rotated": "posed, turned by a uniformly random rotation",
    "lying": "Anny's full body decimated, turned 90° about a random horizontal axis",
    "glb": "Anny's full body decimated, through a y-up GLB file",
    "seams": "posed, its vertices split at UV seams into 8 islands (of the rest pose), through a y-up GLB file",
    "parts": "Anny's full body decimated, with eyeballs and teeth as separate parts",
    "props": "Anny's full body decimated, holding a sword (a separate part, rigid in the right hand)",
    "dense": "Anny's full body subdivided past 50,000 vertices, shuffled",
    "foreign_driver": "the training topology driven by a 24-frame clip of a decimated, shuffled body",
}
OTHER_TOPOLOGY = {"notoes_collapse3pc": "notoes_collapse10pc"}  # else notoes_collapse3pc
FULL_TOPOLOGY = "notoes"
REMESH_FACES = 3000
CARRIED = ("posed", "rotated", "lying", "glb", "seams", "parts", "props")
SEAM_HEIGHTS = (0.3, 0.5, 0.8)  # of the body's height: islands below, between and above, each split left and right
DENSE_VERTICES = 50_000
DENSE_REFINED_FACES = 1000  # the largest faces subdivided a second time: 49,082 vertices once, past 50,000 then
DRIVER_FRAMES = 24
# The parts at Anny's average interocular distance (scaled by each body's), placed and sized on 80
# bodies of the mixed and extreme splits: the eyeballs fill the sockets, the teeth box sits in the
# mouth cavity at least 1 cm from its walls.
INTEROCULAR = 0.06  # metres
EYE_RADIUS = 0.012
EYE_SUBDIVISIONS = 1  # 42 vertices an eyeball: the parts ~6 % of the vertices, as on an artist's mesh (162: 18 %)
TEETH_OFFSET = (0.0, 0.02, -0.065)  # from the eyes' midpoint (Anny faces -y, z up)
TEETH_EXTENTS = (0.03, 0.03, 0.012)
PROP_LENGTH, PROP_WIDTH = 0.8, 0.03  # metres: a sword's blade, out of the palm along Anny's facing (-y)


def remesh(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A quadric decimation of a mesh: (vertices, faces) of its own topology."""
    simplified = trimesh.Trimesh(vertices, faces, process=False).simplify_quadric_decimation(face_count=REMESH_FACES)
    return np.asarray(simplified.vertices, np.float32), np.asarray(simplified.faces, np.int64)


def _face_axes(vertices: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Per face of ``corners (N, 3)`` on ``vertices (..., V, 3)``, its orthonormal axes as rows
    ``(..., N, 3, 3)``: the first edge, the in-plane normal to it, the face normal."""
    a, b, c = (vertices[..., corners[:, k], :] for k in range(3))
    edge = b - a
    normal = np.cross(edge, c - a)
    edge = edge / np.linalg.norm(edge, axis=-1, keepdims=True)
    normal = normal / np.linalg.norm(normal, axis=-1, keepdims=True)
    return np.stack([edge, np.cross(normal, edge), normal], -2)


@dataclass(frozen=True)
class AttachedPoints:
    """Points that a triangle mesh carries into any pose: each one's closest point on the mesh and
    its offset from it in that face's own axes (so the offset turns with the surface there)."""

    surface: SurfacePoints
    offsets: np.ndarray  # (N, 3) float64, in the axes of ``_face_axes``

    @classmethod
    def attach(cls, points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> AttachedPoints:
        """``points (N, 3)`` attached to the mesh (``vertices``, ``faces``)."""
        vertices = np.asarray(vertices, np.float64)
        return cls._at(closest_points(points, vertices, faces), points, vertices, faces)

    @classmethod
    def rigid(cls, points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> AttachedPoints:
        """``points (N, 3)`` attached as one rigid whole to the mesh's point nearest them (a prop in a hand)."""
        vertices = np.asarray(vertices, np.float64)
        surface = closest_points(points, vertices, faces)
        nearest = int(np.linalg.norm(surface.on(vertices, faces) - points, axis=1).argmin())
        grip = SurfacePoints(np.full(len(points), surface.face[nearest]), np.repeat(surface.weights[nearest : nearest + 1],
                                                                                     len(points), 0))
        return cls._at(grip, points, vertices, faces)

    @classmethod
    def _at(cls, surface: SurfacePoints, points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> AttachedPoints:
        """``points`` attached at the surface points ``surface``: their offsets in those faces' axes."""
        axes = _face_axes(vertices, faces[surface.face])
        return cls(surface, np.einsum("nij,nj->ni", axes, np.asarray(points, np.float64) - surface.on(vertices, faces)))

    def on(self, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
        """The points where the mesh ``vertices (..., V, 3)`` carries them -> ``(..., N, 3)`` float32."""
        vertices = np.asarray(vertices, np.float64)
        turned = np.einsum("...nij,ni->...nj", _face_axes(vertices, faces[self.surface.face]), self.offsets)
        return (self.surface.on(vertices, faces) + turned).astype(np.float32)


def rest_bodies(identities: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Anny's full-resolution bodies at rest, where ``BodyModel.pose`` puts them: vertices
    ``(N, V, 3)`` and bone heads ``(N, bones, 3)``."""
    model = _body_model(FULL_TOPOLOGY)._model
    with torch.no_grad():
        rest = model(phenotype_kwargs=torch.from_numpy(np.asarray(identities, np.float32)))
        deltas = torch.eye(4).repeat(len(identities), len(model.bone_labels), 1, 1)
        transforms, bone_poses = model.get_bone_transforms(deltas, rest["rest_bone_poses"])
        vertices = model.get_skinned_vertices(rest["rest_vertices"], transforms)
    return vertices.numpy(), bone_poses[..., :3, 3].numpy()


def extra_parts(heads: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """An artist's separate parts for a body at rest with bone heads ``(bones, 3)``: an eyeball in
    each eye socket and a teeth box in the mouth, sized by its interocular distance -> vertices
    ``(M, 3)`` and faces ``(G, 3)`` numbered from 0."""
    labels = _body_model(FULL_TOPOLOGY).bone_labels
    left, right = heads[labels.index("eye.L")], heads[labels.index("eye.R")]
    scale = float(np.linalg.norm(left - right)) / INTEROCULAR
    eye = trimesh.creation.icosphere(subdivisions=EYE_SUBDIVISIONS, radius=EYE_RADIUS * scale)
    teeth = trimesh.creation.box(extents=scale * np.array(TEETH_EXTENTS))
    parts = [(eye, left), (eye, right), (teeth, (left + right) / 2 + scale * np.array(TEETH_OFFSET))]
    starts = np.cumsum([0] + [len(mesh.vertices) for mesh, _ in parts])
    return (np.concatenate([mesh.vertices + centre for mesh, centre in parts]),
            np.concatenate([mesh.faces + start for (mesh, _), start in zip(parts, starts[:-1], strict=True)]))


def held_prop(heads: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A sword in the right hand of a body at rest with bone heads ``(bones, 3)``: a ``PROP_LENGTH`` stick
    from the palm (between the wrist and the middle finger's base) forward -> vertices ``(8, 3)``, faces."""
    labels = _body_model(FULL_TOPOLOGY).bone_labels
    palm = (heads[labels.index("wrist.R")] + heads[labels.index("finger3-1.R")]) / 2
    blade = trimesh.creation.box(extents=(PROP_WIDTH, PROP_LENGTH, PROP_WIDTH))
    return blade.vertices + palm + (0.0, -PROP_LENGTH / 2, 0.0), np.asarray(blade.faces)


def posed_target_poses(stream: StreamPairs, split: str, epoch: int, indices: Sequence[int]) -> np.ndarray:
    """The ``posed`` targets' poses ``(B, bones, 3)``: one frame of the split's families, upright,
    from a generator of its own per pair (never the split's target pose)."""
    spec = stream.split(split)
    rngs = [_generator(stream.seed, "posed-target", split, int(epoch), int(i)) for i in indices]
    families = [_choose(rng, spec.families) for rng in rngs]
    pose, _ = sample_windows(families, ["upright"] * len(rngs), rngs, 1, _body_model(FULL_TOPOLOGY).bone_labels,
                             spec.actions)
    return pose[:, 0]


def posed_character(stream: StreamPairs, split: str, epoch: int, index: int,
                    topology: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ``posed`` character of a pair before centring, with its truth for a registration: (vertices,
    faces, Anny's body at ``topology`` in the same build and pose ``(V_a, 3)``, in the same coordinates)."""
    draws = stream.draws(split, epoch, [index])
    identity, pose = draws["identities"][:, 1], posed_target_poses(stream, split, epoch, [index])
    full = _body_model(FULL_TOPOLOGY)
    rest, _ = rest_bodies(identity)
    vertices, faces = remesh(rest[0], full.faces)
    character = AttachedPoints.attach(vertices, rest[0], full.faces).on(full.pose(identity, pose)[0], full.faces)
    return character, faces, _body_model(topology).pose(identity, pose)[0]


def split_at_seams(vertices: np.ndarray, faces: np.ndarray, islands: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mesh as a glTF exporter writes it with UV seams between face ``islands``: each island its own copies
    of its vertices (the same positions). (vertices, faces, each new vertex's original)."""
    pieces, new_faces, origin = [], [], []
    for k in np.unique(islands):
        used = np.unique(faces[islands == k])
        renumber = np.full(len(vertices), -1)
        renumber[used] = np.arange(len(used)) + sum(map(len, origin))
        pieces.append(vertices[used])
        new_faces.append(renumber[faces[islands == k]])
        origin.append(used)
    return np.concatenate(pieces), np.concatenate(new_faces), np.concatenate(origin)


def seam_islands(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Per face of an upright z-up body, its island: by height (``SEAM_HEIGHTS``) and side (x)."""
    centres = vertices[faces].mean(1)
    height = (centres[:, 2] - vertices[:, 2].min()) / np.ptp(vertices[:, 2])
    return np.digitize(height, SEAM_HEIGHTS) * 2 + (centres[:, 0] > np.median(vertices[:, 0]))


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """A rotation matrix uniform over SO(3)."""
    return scipy.spatial.transform.Rotation.random(random_state=rng).as_matrix()


def lying_rotation(rng: np.random.Generator) -> np.ndarray:
    """A random heading about z, then 90 degrees about a random horizontal axis: z up becomes horizontal."""
    heading, axis = rng.uniform(0, 2 * np.pi, 2)
    tilt = np.array([np.cos(axis), np.sin(axis), 0.0]) * np.pi / 2
    Rotation = scipy.spatial.transform.Rotation
    return (Rotation.from_rotvec(tilt) * Rotation.from_rotvec([0.0, 0.0, heading])).as_matrix()


def glb_round_trip(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``vertices`` (z up) written to a GLB file in glTF's y-up axes with trimesh, read back with
    ``load_mesh`` and turned z-up again; ValueError unless every vertex came back, in order."""
    with tempfile.TemporaryDirectory(prefix="aniformer-glb-") as scratch:
        path = Path(scratch) / "target.glb"
        trimesh.Trimesh(from_z_up(vertices, "y"), faces, process=False).export(path)
        read, read_faces = load_mesh(path)
    back = to_z_up(read, "y")
    if back.shape != vertices.shape or not np.array_equal(read_faces, faces) or not np.allclose(back, vertices, atol=1e-6):
        raise ValueError(f"the GLB round trip changed the mesh: {len(vertices)} -> {len(read)} vertices")
    return back


def subdivide(frames: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Frames ``(K, V, 3)`` of a mesh subdivided at edge midpoints (linear, so any pose subdivides
    alike): every face once, then the ``DENSE_REFINED_FACES`` largest (in the first frame) again."""
    K, V, _ = frames.shape
    flat = {"frames": np.asarray(frames, np.float64).transpose(1, 0, 2).reshape(V, 3 * K)}
    vertices, faces, flat = trimesh.remesh.subdivide(frames[0], faces, vertex_attributes=flat)
    largest = np.argsort(trimesh.triangles.area(vertices[faces]))[-DENSE_REFINED_FACES:]
    _, faces, flat = trimesh.remesh.subdivide(vertices, faces, largest, vertex_attributes=flat)
    return flat["frames"].reshape(-1, K, 3).transpose(1, 0, 2).astype(np.float32), faces


def _case(target: np.ndarray, faces: np.ndarray, truth: np.ndarray, drive: np.ndarray) -> dict:
    return {"target": center_bbox(target), "faces": faces, "ground_truth": center_bbox(truth),
            "copy_driver": center_bbox(drive)}


def _foreign_driver(stream: StreamPairs, split: str, epoch: int, index: int) -> dict:
    """Pair ``index``'s ``foreign_driver`` case: ``driving (DRIVER_FRAMES, N, 3)`` and ``driving_faces``
    of the driver's own topology besides the target, ground truth and copy-driver on the stream's."""
    clip = copy.copy(stream)  # the same pairs (bodies, target pose), a longer driving window
    clip.window = DRIVER_FRAMES
    draws = clip.draws(split, epoch, [index])
    (drive,), (truth,), (target,) = pose_pairs(_body_model(stream.topology), draws)
    _, T, bones = draws["motion"].shape[:3]
    full = _body_model(FULL_TOPOLOGY)
    driver = full.pose(np.repeat(draws["identities"][:, 0], T, 0), draws["motion"].reshape(T, bones, 3),
                       draws["translation"].reshape(T, 3))
    (rest,), _ = rest_bodies(draws["identities"][:, 0])
    vertices, faces = remesh(rest, full.faces)
    frames = AttachedPoints.attach(vertices, rest, full.faces).on(driver, full.faces)
    perm = _generator(stream.seed, "driver-shuffle", split, int(epoch), int(index)).permutation(len(vertices))
    frames, faces = shuffle_vertices(frames, faces, perm)
    return {**_case(target[0], stream.faces, truth, drive), "driving": center_bbox(frames), "driving_faces": faces}


def variant_pairs(stream: StreamPairs, split: str, epoch: int, indices: Sequence[int],
                  variants: Sequence[str]) -> list[dict]:
    """Per pair: ``driving (T, V, 3)`` at the stream's topology and, per variant, a dict of
    ``target (N, 3)``, ``faces (F, 3)``, ``ground_truth (T, N, 3)`` and ``copy_driver (T, N, 3)``
    (``foreign_driver``: ``T = DRIVER_FRAMES``, and its own ``driving (T, M, 3)`` and
    ``driving_faces``); all bounding-box centred per mesh. Each pair is made alone, so it is the same
    whatever else is drawn with it: Anny's batched bodies differ with the batch at float level, and a
    decimation or a fit turns that into another mesh (docs/results.md)."""
    return [_variant_pair(stream, split, epoch, index, variants) for index in indices]


def _variant_pair(stream: StreamPairs, split: str, epoch: int, index: int, variants: Sequence[str]) -> dict:
    """``variant_pairs``' pair ``index``, its bodies made in a batch of one."""
    draws = stream.draws(split, epoch, [index])
    topologies = {"same": stream.topology, "shuffled": stream.topology,
                  "topology": OTHER_TOPOLOGY.get(stream.topology, "notoes_collapse3pc")}
    needed = {topologies.get(v, FULL_TOPOLOGY) for v in variants if v != "foreign_driver"}
    meshes = {t: [m[0] for m in pose_pairs(_body_model(t), draws)] for t in needed | {stream.topology}}
    driving = center_bbox(meshes[stream.topology][0])
    full = _body_model(FULL_TOPOLOGY)
    carried = set(variants) & set(CARRIED)
    if carried:
        (rest,), (head,) = rest_bodies(draws["identities"][:, 1])
        decimated, decimated_faces = remesh(rest, full.faces)
    if {"posed", "rotated", "seams"} & set(variants):
        (posed,) = full.pose(draws["identities"][:, 1], posed_target_poses(stream, split, epoch, [index]))
    keys = (split, int(epoch), int(index))
    pair = {"driving": driving}
    for variant in variants:
        if variant == "foreign_driver":
            pair[variant] = _foreign_driver(stream, split, epoch, index)
            continue
        drive, truth, target = meshes[topologies.get(variant, FULL_TOPOLOGY)]
        target, faces = target[0], _body_model(topologies.get(variant, FULL_TOPOLOGY)).faces
        if variant == "shuffled":
            perm = _generator(stream.seed, "shuffle", *keys).permutation(len(target))
            _, faces = shuffle_vertices(target, faces, perm)
            target, drive, truth = (x[..., perm, :] for x in (target, drive, truth))
        elif variant == "remeshed":
            remeshed, remeshed_faces = remesh(target, faces)
            on_body = closest_points(remeshed, target, faces)
            drive, truth = (on_body.on(x, faces) for x in (drive, truth))
            target, faces = remeshed, remeshed_faces
        elif variant == "dense":
            frames, faces = subdivide(np.concatenate([target[None], truth, drive]), faces)
            perm = _generator(stream.seed, "dense-shuffle", *keys).permutation(frames.shape[1])
            frames, faces = shuffle_vertices(frames, faces, perm)
            target, truth, drive = frames[0], frames[1 : 1 + len(truth)], frames[1 + len(truth) :]
        elif variant in CARRIED:
            points, faces = decimated, decimated_faces
            if variant == "parts":
                part_points, part_faces = extra_parts(head)
                points, faces = np.concatenate([points, part_points]), np.concatenate([faces, part_faces + len(points)])
            elif variant == "seams":
                points, faces, _ = split_at_seams(points, faces, seam_islands(points, faces))
            carry = [AttachedPoints.attach(points, rest, full.faces)]
            if variant == "props":
                prop_points, prop_faces = held_prop(head)
                carry.append(AttachedPoints.rigid(prop_points, rest, full.faces))
                faces = np.concatenate([faces, prop_faces + len(points)])
            full_target = posed if variant in ("posed", "rotated", "seams") else target
            target, truth, drive = (np.concatenate([c.on(x, full.faces) for c in carry], -2)
                                    for x in (full_target, truth, drive))
            if variant in ("rotated", "lying"):
                rng = _generator(stream.seed, f"{variant}-target", *keys)
                turn = random_rotation(rng) if variant == "rotated" else lying_rotation(rng)
                target = (target @ turn.T).astype(np.float32)
            elif variant in ("glb", "seams"):
                target = glb_round_trip(target, faces)
        pair[variant] = _case(target, faces, truth, drive)
    return pair
