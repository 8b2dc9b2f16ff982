"""An animated target's frames as the motion of its rig (``aniformer.rig.Rig``): joint rotations plus root
translation, and the rig's weights refitted to the clip (``jobs/animate.py --rig``).

1. **Motion** (``fit_motion``): per frame, each joint's rotation relative to its bind local rotation
   and the root's translation, such that linear blend skinning of the rig reproduces the animated
   frames in least squares: started from per-bone Kabsch rotations of the vertices each bone
   dominates, then refined by L-BFGS on all frames at once. ``RigMotion.residual`` is the RMS
   distance of the skinned frames to the animated ones.
2. **Weights and motion together** (``fit_rig``): the weights of each vertex's 4 bones refitted to the
   clip under the fitted motion (``fit_weights``: least squares, pulled towards Anny's, non-negative,
   summing to 1), then the motion refitted from where it was, ``WEIGHT_ROUNDS`` times: alternating
   least squares, as smooth skinning decomposition does (Le & Deng, SIGGRAPH 2012), on a fixed skeleton.
   Joints that turn less than ``STILL_DEGREES`` over the whole clip (toes, fingers, the face in most
   clips) are then held at one rotation and the rest refitted: such a joint needs no animation channel.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import roma
import torch

from aniformer.rig import MAX_INFLUENCES, Rig, forward_kinematics, skin

MOTION_ITERATIONS = 100  # L-BFGS: 13.7 mm RMS on a 30-frame clip, 12.9 at 400 (the frames are not all skinnable)
MOTION_VERTICES = 1000  # target vertices the motion is fitted on (a fixed random subset of larger meshes)
DOMINANT = 0.5  # a vertex with at least this weight on a bone starts that bone's Kabsch rotation
WEIGHT_ROUNDS = 2  # weights then motion refitted: the rig's error to the frames 0.26 -> 0.15 of theirs (validation)
WEIGHT_PRIOR = 1e-4  # m² per frame: the pull of each vertex's weights towards Anny's carried ones
WEIGHT_CHUNK = 8192  # vertices whose normal equations are built at once
STILL_DEGREES = 3.0  # a joint turning less than this from its mean over the clip is held still


@dataclass(frozen=True)
class RigMotion:
    """Per frame: each joint's local rotation ``rotations (N, J, 4)`` (unit quaternions, xyzw, the bind
    local rotation times the fitted turn), the root's position ``root (N, 3)``, the joints' world
    transforms ``world (N, J, 4, 4)`` and the RMS distance (m) of the skinned frames to the animated ones."""

    rotations: np.ndarray
    root: np.ndarray
    world: np.ndarray
    residual: float


def _initial_world_rotations(rig: Rig, target: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """``(N, J, 3, 3)``: per frame, each joint's world rotation from Kabsch on the vertices it dominates
    (the bind rotation times the turn of those vertices); a joint dominating none turns with its parent."""
    from aniformer.registration import kabsch

    N, J = len(frames), len(rig.names)
    turns = np.zeros((N, J, 3, 3))
    dominant = np.where(rig.weights[:, 0] >= DOMINANT, rig.joints[:, 0], -1)
    for j in range(J):
        rows = np.flatnonzero(dominant == j)
        if len(rows) >= 3:
            source = torch.from_numpy(np.asarray(target, np.float64)[rows])[None].expand(N, -1, -1)
            turns[:, j] = kabsch(source, torch.from_numpy(np.asarray(frames, np.float64)[:, rows])).numpy()
        elif rig.parents[j] >= 0:
            turns[:, j] = turns[:, rig.parents[j]]
        else:
            turns[:, j] = kabsch(torch.from_numpy(np.asarray(target, np.float64))[None].expand(N, -1, -1),
                                  torch.from_numpy(np.asarray(frames, np.float64))).numpy()
    return turns @ rig.bind[None, :, :3, :3]


def fit_motion(rig: Rig, target: np.ndarray, frames: np.ndarray, seed: int = 0,
               start: RigMotion | None = None, still: np.ndarray | None = None) -> RigMotion:
    """The joint rotations and root positions whose skinning of ``target (V, 3)`` best reproduces ``frames
    (N, V, 3)`` (module doc), from per-bone Kabsch rotations or from ``start``; the joints of the mask ``still
    (J,)`` are held at ``start``'s mean rotation in every frame. Deterministic for a ``seed``."""
    if start is None:
        world_rotations = _initial_world_rotations(rig, target, frames)
        parent = np.where(rig.parents[None, :, None, None] >= 0, world_rotations[:, np.maximum(rig.parents, 0)],
                          np.eye(3))
        local = torch.from_numpy(np.swapaxes(parent, -1, -2) @ world_rotations).float()  # (N, J, 3, 3)
        root_start = np.asarray(frames, np.float64).mean(1) - (
            world_rotations[:, 0] @ np.linalg.inv(rig.bind[0, :3, :3]) @ (np.asarray(target, np.float64).mean(0)
                                                                          - rig.bind[0, :3, 3]))
    else:
        local, root_start = roma.unitquat_to_rotmat(torch.from_numpy(start.rotations)).float(), start.root
    moving = torch.ones(local.shape[1], 1)
    if still is not None:
        local[:, still] = _mean_rotation(local[:, still])
        moving[still] = 0.0
    rows = np.random.default_rng(seed).permutation(len(target))[:MOTION_VERTICES]
    goal = torch.from_numpy(np.asarray(frames, np.float32)[:, rows])
    turn = torch.zeros(*local.shape[:2], 3, requires_grad=True)  # applied after the start
    root = torch.from_numpy(root_start.astype(np.float32)).requires_grad_(True)
    optimiser = torch.optim.LBFGS([turn, root], max_iter=MOTION_ITERATIONS, line_search_fn="strong_wolfe")

    def closure():
        optimiser.zero_grad()
        world = forward_kinematics(rig, local @ roma.rotvec_to_rotmat(turn * moving), root)
        loss = (skin(rig, target, world, rows) - goal).square().sum(-1).mean()
        loss.backward()
        return loss

    from aniformer.registration import one_thread

    with torch.enable_grad(), one_thread():  # a 30-frame clip's fit on a busy 2-core machine: 84 s on two threads, 4 s on one
        optimiser.step(closure)
    with torch.no_grad():
        rotations = local @ roma.rotvec_to_rotmat(turn * moving)
        world = forward_kinematics(rig, rotations, root)
        residual = float((skin(rig, target, world) - torch.from_numpy(np.asarray(frames, np.float32)))
                         .square().sum(-1).mean().sqrt())
    return RigMotion(roma.rotmat_to_unitquat(rotations).numpy(), root.detach().numpy(), world.numpy(), residual)


def fit_weights(rig: Rig, target: np.ndarray, motion: RigMotion, frames: np.ndarray) -> Rig:
    """``rig`` with each vertex's weights on its (at most 4) bones refitted so that ``motion`` skins ``target (V, 3)``
    into ``frames (N, V, 3)``: per vertex, least squares over the clip plus ``WEIGHT_PRIOR`` times the squared
    distance to the carried weights, non-negative and summing to 1 (an active set: a bone whose weight goes
    negative is dropped and the vertex solved again). Bones a vertex had no weight on stay at 0."""
    skinning = (torch.from_numpy(motion.world).double() @ torch.from_numpy(rig.inverse_bind))[..., :3, :]  # (N, J, 3, 4)
    N, J = skinning.shape[:2]
    # every bone pair's sum over frames of S_j^T S_k, and every bone's S_j^T times each vertex's frames: the
    # normal equations of every vertex come from these without a (vertices x bones x frames) array
    pairs = torch.einsum("njab,nkac->jkbc", skinning, skinning)  # (J, J, 4, 4)
    bones_by_frames = skinning.permute(1, 3, 0, 2).reshape(J * 4, N * 3)
    joints = torch.from_numpy(rig.joints.astype(np.int64))
    prior = torch.from_numpy(rig.weights.astype(np.float64))
    points = torch.from_numpy(np.asarray(target, np.float64))
    goal = torch.from_numpy(np.asarray(frames, np.float64)).permute(0, 2, 1).reshape(N * 3, -1)  # (N*3, V)
    pull = WEIGHT_PRIOR * N
    weights = []
    for lo in range(0, len(points), WEIGHT_CHUNK):
        rows = slice(lo, lo + WEIGHT_CHUNK)
        x = torch.cat([points[rows], torch.ones(len(points[rows]), 1, dtype=points.dtype)], 1)  # (n, 4)
        bones = joints[rows]
        gram = torch.einsum("vb,vklbc,vc->vkl", x, pairs[bones[:, :, None], bones[:, None, :]], x)
        gram = gram + pull * torch.eye(MAX_INFLUENCES, dtype=points.dtype)
        moved = (bones_by_frames @ goal[:, rows]).reshape(J, 4, -1)  # (J, 4, n): S_j^T y summed over frames
        rhs = torch.einsum("vb,vkb->vk", x, moved[bones, :, torch.arange(len(x))[:, None]]) + pull * prior[rows]
        active = prior[rows] > 0
        for _ in range(MAX_INFLUENCES):
            both = active[:, :, None] & active[:, None, :]
            system = torch.zeros(len(gram), MAX_INFLUENCES + 1, MAX_INFLUENCES + 1, dtype=points.dtype)
            system[:, :-1, :-1] = torch.where(both, gram, torch.diag_embed((~active).double()))
            system[:, :-1, -1] = system[:, -1, :-1] = active.double()  # the weights sum to 1
            solved = torch.linalg.solve(system, torch.cat([torch.where(active, rhs, 0.0),
                                                            torch.ones(len(gram), 1, dtype=points.dtype)], 1))[:, :-1]
            negative = active & (solved < 0)
            if not negative.any():
                break
            active &= ~negative
        weights.append(solved.clamp(min=0))
    weights = torch.cat(weights)
    weights = (weights / weights.sum(1, keepdim=True)).float().numpy()
    order = np.argsort(-weights, 1, kind="stable")  # the largest first, as build_rig's
    weights, joints = np.take_along_axis(weights, order, 1), np.take_along_axis(rig.joints, order, 1)
    weights[:, 0] = 1 - weights[:, 1:].sum(1)  # exactly 1 in float32 (validators check the sum)
    return dataclasses.replace(rig, joints=np.where(weights > 0, joints, 0).astype(rig.joints.dtype), weights=weights)


def fit_rig(rig: Rig, target: np.ndarray, frames: np.ndarray, seed: int = 0) -> tuple[Rig, RigMotion]:
    """``rig`` with refitted weights and the motion that skins ``target`` into ``frames`` (module doc, step 2)."""
    motion = fit_motion(rig, target, frames, seed)
    for _ in range(WEIGHT_ROUNDS):
        rig = fit_weights(rig, target, motion, frames)
        motion = fit_motion(rig, target, frames, seed, start=motion)
    rotations = roma.unitquat_to_rotmat(torch.from_numpy(motion.rotations)).double()
    from_mean = rotations.transpose(-1, -2) @ _mean_rotation(rotations)
    still = np.degrees(roma.rotmat_to_rotvec(from_mean).norm(dim=-1).amax(0).numpy()) < STILL_DEGREES
    return rig, fit_motion(rig, target, frames, seed, start=motion, still=still)


def _mean_rotation(rotations: torch.Tensor) -> torch.Tensor:
    """``(N, J, 3, 3) -> (J, 3, 3)``: each joint's chordal mean rotation over the frames."""
    return roma.special_procrustes(rotations.mean(0))
