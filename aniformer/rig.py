"""A rig for an animated target: Anny's skeleton fitted into it and Anny's skinning weights carried onto its
vertices (``jobs/animate.py --rig``); ``aniformer.rig_motion`` fits the animation as its joint rotations.

1. **Skeleton** (``build_rig``): Anny's build and pose are fitted to the target's template-level vertices
   (its own vertices on an Anny topology, or its ``aniformer.correspondence.Correspondence.template``) by vertex
   least squares: one-to-one correspondences, so unlike the registration no search is needed. Anny's
   posed bone frames there are the joints' bind transforms; the target's vertices are the bind pose.
2. **Weights**: Anny's per-vertex bone weights, carried to each target vertex by the barycentric
   weights of its point on the template, the 4 largest kept and normalised (glTF's and most engines'
   limit). Bones no vertex depends on, and nothing below them does, are pruned (toes, most of the face).

Joint names are Anny's bone labels, or with ``bone_names="mixamo"`` Mixamo's (``mixamorig:Hips``,
``mixamorig:LeftArm`` ...) where a Mixamo bone has an Anny counterpart (``MIXAMO``), so retargeting
tools that know Mixamo's skeleton map it without a bone map; Anny's extra bones (a second spine and
neck segment, twist bones, metacarpals) keep their labels.

Coordinates: metres, z up (the project's axes); writers convert (``aniformer.io.glb.write_rigged_glb``,
``aniformer.io.bvh.write_bvh``).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import roma
import torch

MAX_INFLUENCES = 4  # bones per vertex: glTF's JOINTS_0 / WEIGHTS_0 hold 4
PRUNE_WEIGHT = 0.01  # a bone whose largest kept weight is below this moves nothing visible
SKELETON_STEPS = 300
_MIXAMO_SIDED = {"clavicle": "Shoulder", "upperarm01": "Arm", "lowerarm01": "ForeArm", "wrist": "Hand",
                 "upperleg01": "UpLeg", "lowerleg01": "Leg", "foot": "Foot", "eye": "Eye",
                 **{f"finger{k}-{n}": f"Hand{finger}{n}" for k, finger in enumerate(
                     ("Thumb", "Index", "Middle", "Ring", "Pinky"), 1) for n in (1, 2, 3)}}
MIXAMO = {"root": "Hips", "spine05": "Spine", "spine03": "Spine1", "spine01": "Spine2", "neck01": "Neck", "head": "Head",
          **{f"{anny}.{side[0]}": f"{side}{mixamo}" for anny, mixamo in _MIXAMO_SIDED.items() for side in ("Left", "Right")}}


@dataclass(frozen=True)
class Rig:
    """Joints ``names`` with ``parents`` (-1: the root; parents come first), their bind transforms
    ``bind (J, 4, 4)`` (world, the target's coordinates) and per target vertex ``joints (V, 4)`` and
    ``weights (V, 4)`` (float32, rows summing to 1)."""

    names: tuple[str, ...]
    parents: np.ndarray
    bind: np.ndarray
    joints: np.ndarray
    weights: np.ndarray

    @functools.cached_property
    def local_bind(self) -> np.ndarray:
        """``(J, 4, 4)``: each joint's bind transform relative to its parent's (the root's: world)."""
        parent = np.where(self.parents[:, None, None] >= 0, self.bind[np.maximum(self.parents, 0)], np.eye(4))
        return np.linalg.inv(parent) @ self.bind

    @functools.cached_property
    def inverse_bind(self) -> np.ndarray:
        """``(J, 4, 4)``: the inverse bind matrices (world to each joint's bind frame)."""
        return np.linalg.inv(self.bind)

    @functools.cached_property
    def depth(self) -> np.ndarray:
        """``(J,)``: each joint's number of ancestors (parents come first)."""
        depth = np.zeros(len(self.parents), int)
        for j in range(1, len(self.parents)):
            depth[j] = depth[self.parents[j]] + 1
        return depth


def _body(topology: str):
    from aniformer.synth.bodies import BodyModel

    return BodyModel(topology)


def _fit_skeleton(template_vertices: np.ndarray, topology: str) -> torch.Tensor:
    """Anny's posed bone frames ``(B, 4, 4)`` at the build and pose that best reproduce ``template_vertices
    (V_a, 3)`` (Anny's vertex order), vertex to vertex; the root turned by Kabsch first."""
    from aniformer.registration import anny_template, kabsch, one_thread

    template = anny_template(topology)
    target = torch.from_numpy(np.asarray(template_vertices, np.float32))[None]
    with torch.no_grad():
        average = template.vertices(torch.full((1, 6), 0.5), torch.zeros(1, template.bones, 3))
    rotvecs = torch.zeros(1, template.bones, 3)
    root = template.bone_labels.index("root")
    rotvecs[:, root] = roma.rotmat_to_rotvec(kabsch(average, target))
    phenotype = torch.zeros(1, 6)
    shift = (target.mean(1) - (roma.rotvec_to_rotmat(rotvecs[:, root]) @ average.mean(1)[..., None])[..., 0])[:, None]
    params = [p.requires_grad_(True) for p in (phenotype, rotvecs, shift)]
    optimiser = torch.optim.Adam(params, lr=0.02)
    with torch.enable_grad(), one_thread():
        for _ in range(SKELETON_STEPS):
            loss = (template.vertices(torch.sigmoid(params[0]), params[1]) + params[2] - target).square().sum(-1).mean()
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
    with torch.no_grad():
        rest = template.model(phenotype_kwargs=torch.sigmoid(params[0]))
        deltas = torch.eye(4).repeat(1, template.bones, 1, 1)
        deltas[..., :3, :3] = roma.rotvec_to_rotmat(params[1])
        _, poses = template.model.get_bone_transforms(deltas, rest["rest_bone_poses"])
        poses = poses.clone()
        poses[..., :3, 3] += params[2]
    return poses[0].double()


def build_rig(target: np.ndarray, template_vertices: np.ndarray, topology: str, on_template=None,
              bone_names: str = "anny") -> Rig:
    """The rig of ``target (V, 3)``: ``template_vertices (V_a, 3)`` are its Anny-topology vertices (module doc);
    ``on_template`` (``surface.SurfacePoints``) places each target vertex on the template, None when the
    target is that topology itself; ``bone_names``: "anny" or "mixamo" (module doc)."""
    body = _body(topology)
    model = body._model
    dense = np.zeros((body.num_vertices, len(body.bone_labels)))
    np.put_along_axis(dense, model.vertex_bone_indices.numpy(), model.vertex_bone_weights.numpy().astype(np.float64), 1)
    if on_template is not None:  # the template's weights at each vertex's point on it
        dense = np.einsum("vk,vkb->vb", on_template.weights, dense[body.faces[on_template.face]])
    joints = np.argsort(-dense, 1)[:, :MAX_INFLUENCES]
    weights = np.take_along_axis(dense, joints, 1)
    weights /= weights.sum(1, keepdims=True)
    parents = np.array(body.bone_parents)
    used = np.zeros(len(parents), bool)
    used[np.unique(joints[weights >= PRUNE_WEIGHT])] = True
    for bone in range(len(parents) - 1, 0, -1):  # a used bone's ancestors are needed to move it
        used[parents[bone]] |= used[bone]
    used[0] = True
    kept = np.flatnonzero(used)
    index = np.full(len(parents), -1)
    index[kept] = np.arange(len(kept))
    weights = np.where(used[joints], weights, 0.0)  # influences of pruned bones (below PRUNE_WEIGHT) dropped
    weights = (weights / weights.sum(1, keepdims=True)).astype(np.float32)
    weights[:, 0] = 1 - weights[:, 1:].sum(1)  # exactly 1 in float32 (validators check the sum)
    poses = _fit_skeleton(template_vertices, topology).numpy()
    names = {"anny": {}, "mixamo": {k: f"mixamorig:{v}" for k, v in MIXAMO.items()}}[bone_names]
    return Rig(tuple(names.get(body.bone_labels[b], body.bone_labels[b]) for b in kept), index[parents[kept]], poses[kept],
               np.where(weights > 0, index[joints], 0).astype(np.uint16), weights)


def forward_kinematics(rig: Rig, rotations: torch.Tensor, root: torch.Tensor) -> torch.Tensor:
    """World transforms ``(N, J, 4, 4)`` of local rotation matrices ``rotations (N, J, 3, 3)`` and root
    positions ``root (N, 3)``, the other joints at their bind offsets from their parents; one batched
    product per depth of the tree."""
    N, J = rotations.shape[:2]
    offsets = torch.from_numpy(rig.local_bind[:, :3, 3]).to(rotations.dtype).expand(N, J, 3)
    offsets = torch.cat([root[:, None], offsets[:, 1:]], 1)  # the root (joint 0) sits where the motion puts it
    local = torch.cat([torch.cat([rotations, offsets[..., None]], -1),
                       torch.tensor([0.0, 0, 0, 1], dtype=rotations.dtype).expand(N, J, 1, 4)], -2)
    world = [local[:, 0]] + [None] * (J - 1)
    for level in range(1, rig.depth.max() + 1):
        joints = np.flatnonzero(rig.depth == level)
        moved = torch.stack([world[p] for p in rig.parents[joints]], 1) @ local[:, joints]
        for k, j in enumerate(joints):
            world[j] = moved[:, k]
    return torch.stack(world, 1)


def skin(rig: Rig, target: np.ndarray | torch.Tensor, world: torch.Tensor, vertices: np.ndarray | None = None,
         chunk: int = 64) -> torch.Tensor:
    """Linear blend skinning: ``target``'s vertices (or the subset ``vertices``) moved by joint world
    transforms ``world (N, J, 4, 4)`` -> ``(N, V, 3)``, ``chunk`` frames at a time. The weights as a dense
    (V, J) matrix: one matrix product blends every vertex's transforms, forwards and backwards."""
    rows = slice(None) if vertices is None else vertices
    points = torch.as_tensor(np.asarray(target)[rows], dtype=world.dtype)
    dense = np.zeros((len(points), len(rig.names)), np.float32)
    np.add.at(dense, (np.arange(len(points))[:, None], rig.joints[rows].astype(np.int64)), rig.weights[rows])
    dense = torch.from_numpy(dense).to(world.dtype)
    skinning = (world @ torch.from_numpy(rig.inverse_bind).to(world.dtype))[..., :3, :]  # (N, J, 3, 4)
    out = []
    for lo in range(0, len(world), chunk):
        blended = (dense @ skinning[lo:lo + chunk].flatten(2)).unflatten(-1, (3, 4))  # (n, V, 3, 4)
        out.append((blended[..., :3] * points[:, None]).sum(-1) + blended[..., 3])
    return torch.cat(out)
