"""Correspondence between any mesh and an Anny topology, so the model can animate any target.

The model works on one topology with vertex correspondence between driver and target (vertex
``i`` is the same body point in both; ``aniformer/transfer.py``). A user's character has its own
vertex count, order and connectivity. ``Correspondence`` fits Anny's body at the model's topology onto
the mesh and keeps the two embeddings that carry motion across:

1. *fit*: Anny's phenotype (build), its 104 bone rotations and a global heading, then small
   smooth per-vertex offsets, minimising the symmetric Chamfer distance between the two surfaces
   (four headings about z are tried at once; characters come upright, z up like the driver);
2. *template on mesh*: each fitted template vertex snapped to its closest point on the mesh
   (a face and barycentric weights), so ``to_template`` reads any frame of the mesh's topology
   on Anny's (a driving sequence keeps its topology, so one fit serves every frame);
3. *mesh on template*: each mesh vertex's closest point on the template and its offset from it,
   so ``from_template`` carries a posed template back: the vertex rides its point, and its offset
   turns with the template's rotation there (the one-ring rotations of the face's corners,
   blended). Solving for the mesh's own edges turned by those rotations (as-rigid-as-possible)
   was measured worse: 1.3-7.1 against 1.0-1.2 PMD of carry-back error (docs/results.md).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import roma
import scipy.spatial
import torch
import trimesh

from aniformer.transfer import mesh_edges, vertex_rotations

HEADINGS = (0.0, np.pi / 2, np.pi, 3 * np.pi / 2)
TEMPLATE_SAMPLES = 2000  # points on the template surface per Chamfer evaluation
MESH_SAMPLES = 3000  # points on the mesh surface, besides its vertices (without them: 2x the error)
POSE_PRIOR = 1e-4  # per rad^2 of bone rotation: keeps unconstrained bones (fingers, face) at rest


@dataclass(frozen=True)
class SurfacePoints:
    """Points on a triangle mesh as a face index and barycentric weights, valid in any pose."""

    face: np.ndarray  # (N,) int64
    weights: np.ndarray  # (N, 3) float64, rows sum to 1

    def on(self, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
        """The points on ``vertices (..., V, 3)`` of the mesh ``faces`` -> ``(..., N, 3)``."""
        corners = np.asarray(vertices)[..., faces[self.face], :]  # (..., N, 3, 3)
        return np.einsum("...nkc,nk->...nc", corners, self.weights).astype(np.asarray(vertices).dtype)


def closest_points(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> SurfacePoints:
    """Each of ``points (N, 3)`` as its closest point on the mesh (``vertices``, ``faces``)."""
    mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), faces, process=False)
    closest, _, face = trimesh.proximity.closest_point(mesh, np.asarray(points, np.float64))
    with np.errstate(divide="ignore", invalid="ignore"):  # degenerate triangles: NaN, replaced below
        weights = np.nan_to_num(trimesh.triangles.points_to_barycentric(mesh.triangles[face], closest), nan=1 / 3)
    weights = np.clip(weights, 0.0, 1.0)
    return SurfacePoints(np.asarray(face, np.int64), weights / weights.sum(1, keepdims=True))


def _chamfer(a: torch.Tensor, b: torch.Tensor, b_tree: scipy.spatial.cKDTree) -> torch.Tensor:
    """Symmetric squared Chamfer distance per batch row: ``a (B, N, 3)``, ``b (M, 3)`` (with its
    k-d tree) -> ``(B,)``. Nearest neighbours come from k-d trees, then only the distances to them
    are differentiated (a dense distance matrix costs ~1 s per step)."""
    points = a.detach().numpy()
    nearest_b = torch.from_numpy(np.stack([b_tree.query(p)[1] for p in points]))  # (B, N)
    nearest_a = torch.from_numpy(np.stack([scipy.spatial.cKDTree(p).query(b.numpy())[1] for p in points]))  # (B, M)
    to_b = (a - b[nearest_b]).square().sum(-1).mean(1)
    to_a = (b[None] - torch.gather(a, 1, nearest_a[..., None].expand(-1, -1, 3))).square().sum(-1).mean(1)
    return to_b + to_a


class _Template:
    """Anny at one topology as a differentiable function of (phenotype, bone rotations)."""

    def __init__(self, topology: str):
        from aniformer.synth.bodies import BodyModel

        body = BodyModel(topology)
        self.model, self.faces, self.bones = body._model, body.faces, len(body.bone_labels)
        rng = np.random.default_rng(0)  # fixed sample layout: the fit is deterministic
        self.sample_faces = torch.from_numpy(self.faces[rng.integers(0, len(self.faces), TEMPLATE_SAMPLES)])
        weights = rng.dirichlet(np.ones(3), TEMPLATE_SAMPLES)
        self.sample_weights = torch.from_numpy(weights.astype(np.float32))

    def vertices(self, phenotype: torch.Tensor, rotvecs: torch.Tensor) -> torch.Tensor:
        rest = self.model(phenotype_kwargs=phenotype)
        deltas = torch.eye(4).repeat(len(rotvecs), self.bones, 1, 1)
        deltas = torch.cat([torch.cat([roma.rotvec_to_rotmat(rotvecs), deltas[..., :3, 3:]], -1), deltas[..., 3:, :]], -2)
        transforms, _ = self.model.get_bone_transforms(deltas, rest["rest_bone_poses"])
        return self.model.get_skinned_vertices(rest["rest_vertices"], transforms)

    def samples(self, vertices: torch.Tensor) -> torch.Tensor:
        return torch.cat([vertices, (vertices[:, self.sample_faces] * self.sample_weights[..., None]).sum(2)], 1)


@functools.cache
def _template(topology: str) -> _Template:
    return _Template(topology)


def _fit_body(template: _Template, points: torch.Tensor, tree, start: list[torch.Tensor], steps: int):
    """Adam on (phenotype logits, bone rotations, shift) of each batch row from ``start``: (the
    parameters, the posed vertices, the loss per row)."""
    phenotype, rotvecs, shift = params = [p.detach().clone().requires_grad_(True) for p in start]
    optimiser = torch.optim.Adam(params, lr=0.03)
    for _ in range(steps):
        posed = template.vertices(torch.sigmoid(phenotype), rotvecs)
        posed = posed - (posed.amin(1, keepdim=True) + posed.amax(1, keepdim=True)) / 2 + shift
        loss = _chamfer(template.samples(posed), points, tree) + POSE_PRIOR * rotvecs[:, 1:].square().sum((1, 2))
        optimiser.zero_grad()
        loss.sum().backward()
        optimiser.step()
    return params, posed.detach(), loss.detach()


def fit_template(vertices: np.ndarray, faces: np.ndarray, topology: str, *, steps: tuple[int, int, int] = (40, 110, 100),
                 seed: int = 0) -> np.ndarray:
    """Anny at ``topology`` fitted onto a mesh -> template vertices ``(V_a, 3)`` float32 in the
    mesh's coordinates. ``steps``: of the four headings at once, of the best one, of the offsets."""
    template = _template(topology)
    mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), faces, process=False)
    centre = (mesh.bounds[0] + mesh.bounds[1]) / 2
    points, _ = trimesh.sample.sample_surface(mesh, MESH_SAMPLES, seed=seed)
    points = torch.from_numpy(np.concatenate([points, mesh.vertices]) - centre).float()
    tree = scipy.spatial.cKDTree(points.numpy())
    rotvecs = torch.zeros(len(HEADINGS), template.bones, 3)
    rotvecs[:, 0, 2] = torch.tensor(HEADINGS)
    start = [torch.zeros(len(HEADINGS), 6), rotvecs, torch.zeros(len(HEADINGS), 1, 3)]  # logit 0: Anny's average
    with torch.enable_grad():
        params, _, loss = _fit_body(template, points, tree, start, steps[0])
        best = int(loss.argmin())
        _, posed, _ = _fit_body(template, points, tree, [p[best : best + 1] for p in params], steps[1])
        offsets = torch.zeros_like(posed, requires_grad=True)
        i, j = (torch.from_numpy(e) for e in mesh_edges(template.faces, posed.shape[1]))
        optimiser = torch.optim.Adam([offsets], lr=2e-3)
        for _ in range(steps[2]):  # small smooth offsets: what the body model's shape space misses
            smooth = (offsets[:, i] - offsets[:, j]).square().sum(-1).mean()
            loss = _chamfer(template.samples(posed + offsets), points, tree) + 10.0 * smooth
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
    return ((posed + offsets).detach()[0].numpy() + centre).astype(np.float32)


class Correspondence:
    """A mesh registered to an Anny topology: read its frames on the template, carry poses back.

    ``template_faces`` is the Anny topology's; ``template`` the fitted template's vertices on the
    mesh's surface; ``rms`` the root-mean-square distance of the fitted template's vertices to the
    mesh's surface and of the mesh's vertices to the template's (mesh units)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, topology: str, **fit_options):
        self.vertices = np.asarray(vertices, np.float32)
        self.faces = np.asarray(faces, np.int64)
        self.template_faces = _template(topology).faces
        fitted = fit_template(self.vertices, self.faces, topology, **fit_options)
        self.template_on_mesh = closest_points(fitted, self.vertices, self.faces)
        self.template = self.to_template(self.vertices)
        self.mesh_on_template = closest_points(self.vertices, self.template, self.template_faces)
        back = self.mesh_on_template.on(self.template, self.template_faces)
        gaps = np.concatenate([np.linalg.norm(fitted - self.template, axis=1), np.linalg.norm(self.vertices - back, axis=1)])
        self.rms = float(np.sqrt(np.square(gaps).mean()))

    def to_template(self, frames: np.ndarray) -> np.ndarray:
        """Frames ``(..., N, 3)`` of the mesh's topology as ``(..., V_a, 3)`` on Anny's."""
        return self.template_on_mesh.on(frames, self.faces)

    def from_template(self, posed: np.ndarray, chunk: int = 32) -> np.ndarray:
        """The mesh in the poses of ``posed (T, V_a, 3)`` (the template moved) -> ``(T, N, 3)``: each
        vertex rides its template point, its offset from it turned by the template's local rotation
        (``chunk`` frames at a time: a frame holds a 3x3 rotation per vertex)."""
        rest = torch.from_numpy(self.template.astype(np.float64))
        corner_index = torch.from_numpy(self.template_faces[self.mesh_on_template.face])  # (N, 3)
        weights = torch.from_numpy(self.mesh_on_template.weights)
        offset = torch.from_numpy(self.vertices - self.mesh_on_template.on(self.template, self.template_faces)).double()
        out = []
        for lo in range(0, len(posed), chunk):
            frames = np.asarray(posed[lo : lo + chunk], np.float64)
            rotations = vertex_rotations(rest, torch.from_numpy(frames), self.template_faces)
            turn = roma.special_procrustes(torch.einsum("tnkab,nk->tnab", rotations[:, corner_index], weights))
            moved = (turn @ offset[..., None])[..., 0].numpy()
            out.append(self.mesh_on_template.on(frames, self.template_faces) + moved)
        return np.concatenate(out).astype(np.float32)
