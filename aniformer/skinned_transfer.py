"""Motion carried through Anny's skeleton, no learning: Anny fitted to every driving frame and to the target by
vertex correspondence (both meshes are on one of Anny's topologies), then the target's own vertices unskinned
from its fitted pose and skinned in each driving frame's fitted pose, on the target's fitted body.

It is what a rig does (fit the driver's joint rotations, play them on the target's skeleton), and it is
exact where the meshes are Anny's own bodies posed by Anny's skinning, as the stream's ground truth is: the
yardstick for what a learned model adds on such data (docs/results.md). jobs/animate.py runs it instead of a
network with ``--checkpoint skinned`` (``skinned_model``): every frame of the clip fitted at once.
"""

from __future__ import annotations

from dataclasses import dataclass

import roma
import torch

from aniformer.animation_run import anny_topology
from aniformer.geometry import center_bbox
from aniformer.registration import anny_template, kabsch, one_thread

STEPS = (600, 600)  # Adam steps with the build free, then with it held
LR = 0.1  # cosine-annealed to LR / 30 in each round
BUILD_LR = 0.3  # measured on validation pairs: the build converges slowest
REFERENCE = "skinned"  # jobs/animate.py's --checkpoint that names this method instead of a checkpoint
TOPOLOGY = "notoes_collapse3pc"  # where it runs when neither mesh is Anny's: the shipped model's topology


def _adam(params: list[torch.Tensor], steps: int, loss_of, lrs=None) -> None:
    optimiser = torch.optim.Adam([{"params": [p], "lr": lr} for p, lr in zip(params, lrs or [LR] * len(params))])
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimiser, steps, eta_min=LR / 30)
    for _ in range(steps):
        optimiser.zero_grad()
        loss_of().sum().backward()
        optimiser.step()
        schedule.step()


@one_thread()  # all of it: the fit's path depends on the last bits of its start (measured: 2.4 cm apart on 1 or 2 threads)
def fit_poses(meshes: torch.Tensor, groups: torch.Tensor, topology: str,
              steps: tuple[int, int] = STEPS) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Anny fitted to ``meshes (N, V, 3)`` of ``topology`` by vertex correspondence, one build per group
    (``groups (N,)`` in ``0..G-1``: the frames of one body share it): (phenotypes ``(G, 6)``, bone rotations
    ``(N, bones, 3)``, each mesh's mean squared vertex distance ``(N,)``). Centroids are matched, so any
    translation or centring of the meshes is ignored; the root starts turned onto each mesh (Kabsch)."""
    template = anny_template(topology)
    target = meshes.float() - meshes.float().mean(1, keepdim=True)
    rest_pose = torch.zeros(len(meshes), template.bones, 3)
    with torch.no_grad():
        average = template.vertices(torch.full((1, 6), 0.5), rest_pose[:1])
    rest_pose[:, template.bone_labels.index("root")] = roma.rotmat_to_rotvec(kabsch(average.expand(len(meshes), -1, -1), target))
    logits = torch.zeros(int(groups.max()) + 1, 6, requires_grad=True)
    rotvecs = rest_pose.requires_grad_(True)

    def distance(posed: torch.Tensor) -> torch.Tensor:
        return (posed - posed.mean(1, keepdim=True) - target).square().sum(-1).mean(1)

    def posed(rest: dict) -> torch.Tensor:  # each group's rest body (Anny's costliest part) made once
        bones = {"rest_bone_poses": rest["rest_bone_poses"][groups]}
        return template.model.get_skinned_vertices(rest["rest_vertices"][groups], template._skeleton(bones, rotvecs))

    with torch.enable_grad():
        _adam([logits, rotvecs], steps[0], lambda: distance(posed(template.rest(torch.sigmoid(logits)))),
              [BUILD_LR, LR])
        phenotypes = torch.sigmoid(logits).detach()
        rest = template.rest(phenotypes)
        rest = {k: rest[k].detach() for k in ("rest_vertices", "rest_bone_poses")}
        _adam([rotvecs], steps[1], lambda: distance(posed(rest)))
    with torch.no_grad():
        residual = distance(posed(rest))
    return phenotypes, rotvecs.detach(), residual


@one_thread()  # the same frames whatever the caller's threads (an animate process, a Ray actor)
def skinned_transfer(driving: torch.Tensor, target: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """The target in the pose of each driving frame: ``driving (B, T, V, 3)``, ``target (B, V, 3)``, both on the
    Anny topology of ``faces (F, 3)`` (or ``(B, F, 3)``) -> ``(B, T, V, 3)`` float32, bounding-box centred."""
    B, T, V, _ = driving.shape
    faces = faces[0] if faces.dim() == 3 else faces
    topology = anny_topology(driving[0, 0], faces.cpu().numpy())
    if topology is None:
        raise ValueError(f"a skinned transfer needs meshes on one of Anny's topologies; got {V} vertices")
    template = anny_template(topology)
    meshes = torch.cat([driving.reshape(B * T, V, 3), target]).cpu().float()
    groups = torch.cat([torch.arange(B).repeat_interleave(T), B + torch.arange(B)])
    phenotypes, rotvecs, _ = fit_poses(meshes, groups, topology)
    body = phenotypes[B:]  # the target's build, in its own pose and in every driving pose
    with torch.no_grad():
        rest, skinning = template.vertex_transforms(torch.cat([body, body.repeat_interleave(T, 0)]),
                                                    torch.cat([rotvecs[B * T:], rotvecs[: B * T]]))
    skinning = skinning.double()
    posed = (skinning[..., :3, :3] @ rest.double()[..., None])[..., 0] + skinning[..., :3, 3]  # Anny, fitted
    fitted, driven = posed[:B], posed[B:].reshape(B, T, V, 3)
    # what Anny's body misses of the target, carried by each vertex's skinning rotation (a blend's nearest
    # rotation: a blend of two rotations far apart is near singular, and inverting it tears the mesh)
    turns = roma.special_procrustes(skinning[..., :3, :3])
    own = target.cpu().double()
    own = own - own.mean(1, keepdim=True) + fitted.mean(1, keepdim=True)
    at_rest = (turns[:B].transpose(-1, -2) @ (own - fitted)[..., None])
    moved = driven + (turns[B:].reshape(B, T, V, 3, 3) @ at_rest[:, None])[..., 0]
    return center_bbox(moved).float().to(driving.device)


@dataclass(frozen=True)
class ClipConfig:
    """What jobs/animate.py reads of a model's config, for the skinned transfer: one window of the whole clip
    (its frames' fits share the driver's build) and a per-vertex output (other topologies are registered)."""

    window: int = 0  # 0: as many frames as the clip has
    output: str = "skinned"

    def output_frames(self) -> slice:
        return slice(None)


class SkinnedTransfer:
    """``skinned_transfer`` where jobs/animate.py expects a model: ``(driving, target, faces) -> frames``."""

    config = ClipConfig()

    def to(self, device) -> SkinnedTransfer:  # it fits on the CPU and returns frames on the driver's device
        return self

    def __call__(self, driving: torch.Tensor, target: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
        return skinned_transfer(driving, target, faces)


def skinned_model() -> tuple[SkinnedTransfer, dict]:
    """(model, state) as ``aniformer.checkpoint.model_from_checkpoint`` gives a checkpoint's: what animation.json
    records of the method, and the topology it runs on when neither mesh is Anny's."""
    return SkinnedTransfer(), {"config": {"model": {"method": "skinned transfer", "steps": list(STEPS)},
                                          "data": {"topology": TOPOLOGY}}, "epoch": None}
