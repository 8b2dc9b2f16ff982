"""Deformation transfer between meshes of one topology: the target's shape in the driver's pose.

The geometric prior under ``AniFormerConfig(output="transfer")``. With vertex correspondence
(driver and target share a topology and vertex order), every vertex ``i`` of the driver is the
same body point as vertex ``i`` of the target, so the pose can be moved over edge by edge, as in
as-rigid-as-possible deformation (Sorkine & Alexa 2007) and deformation transfer (Sumner &
Popović 2004):

1. per vertex, the rotation ``R_i`` that best maps the target's one-ring edges onto the driver's
   (orthogonal Procrustes, Kabsch);
2. the mesh ``y`` whose edges are the target's edges turned by those rotations, in the least-squares
   sense: ``L y = b`` with ``L`` the graph Laplacian of the topology and
   ``b_i = sum_j (R_i + R_j) / 2 (x_i - x_j)``; the solution is unique up to a translation, and is
   bounding-box centred like every mesh the model sees.

The edge lengths (the body's build) come from the target, the rotations (the pose and orientation)
from the driver, whatever the pose; no learning is involved. The model then learns a correction
on top (joints, where one rotation per vertex is not the whole story). ``L`` depends on the faces
only: it is factorised once per topology and process, sparse (SuperLU with a minimum-degree
ordering), so memory grows about linearly with V; the solve runs on the CPU for tensors on any
device (docs/benchmarks.md: the factor's size and the solve's time from 369 to 50k vertices).
"""

from __future__ import annotations

import functools

import numpy as np
import roma
import scipy.sparse
import scipy.sparse.linalg
import torch
from threadpoolctl import ThreadpoolController


def mesh_edges(faces: np.ndarray, num_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """The unique edges ``(i, j)``, ``i < j``, of a triangle mesh, sorted by ``i`` then ``j`` (``num_vertices``
    is for the caller's checks)."""
    start, end = faces.reshape(-1).astype(np.int64), faces[:, [1, 2, 0]].reshape(-1).astype(np.int64)
    base = int(faces.max()) + 1 if len(faces) else 1
    # one int64 key per edge: a 1-d unique is ~4x faster than np.unique(axis=0) on pairs (docs/benchmarks.md)
    return np.divmod(np.unique(np.minimum(start, end) * base + np.maximum(start, end)), base)


_THREADPOOLS = ThreadpoolController()


@functools.lru_cache(maxsize=8)
def _topology(faces_bytes: bytes, num_faces: int, num_vertices: int):
    """(edge starts, edge ends, sparse LU factor of L + eps I) of a triangle mesh topology."""
    faces = np.frombuffer(faces_bytes, dtype=np.int64).reshape(num_faces, 3)
    i, j = mesh_edges(faces, num_vertices)
    adjacency = scipy.sparse.coo_matrix((np.ones(len(i)), (i, j)), shape=(num_vertices,) * 2).tocsr()
    adjacency = adjacency + adjacency.T
    degree = np.asarray(adjacency.sum(1)).ravel()
    # eps pins the free translation (L's null space); it only shifts the result, which is centred after
    system = scipy.sparse.diags(degree + 1e-8 * degree.mean()) - adjacency
    factor = scipy.sparse.linalg.splu(system.tocsc(), permc_spec="MMD_AT_PLUS_A")
    return torch.from_numpy(i), torch.from_numpy(j), factor


def _rotations(source: torch.Tensor, posed: torch.Tensor, i: torch.Tensor, j: torch.Tensor) -> torch.Tensor:
    """Per vertex, the rotation that best turns the source's one-ring edges onto the posed mesh's."""
    source_edges, posed_edges = source[..., j, :] - source[..., i, :], posed[..., j, :] - posed[..., i, :]
    outer = posed_edges[..., :, None] * source_edges[..., None, :]  # sum of d e^T -> R with R e ~ d
    cross = torch.zeros(*outer.shape[:-3], source.shape[-2], 3, 3, dtype=outer.dtype, device=outer.device)
    cross.index_add_(cross.dim() - 3, i, outer).index_add_(cross.dim() - 3, j, outer)
    return roma.special_procrustes(cross)


def vertex_rotations(source: torch.Tensor, posed: torch.Tensor, faces: np.ndarray) -> torch.Tensor:
    """``(..., V, 3, 3)``: per vertex of a mesh moved from ``source (..., V, 3)`` to ``posed (..., V, 3)``
    (broadcast), the rotation of its one-ring."""
    i, j = (torch.from_numpy(e).to(posed.device) for e in mesh_edges(np.asarray(faces, np.int64), posed.shape[-2]))
    source, posed = torch.broadcast_tensors(source.double(), posed.double())
    return _rotations(source, posed, i, j)


def deformation_transfer(driving: torch.Tensor, target: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """The target mesh in the pose of each driving frame: ``driving (B, T, V, 3)``, ``target (B, V, 3)``,
    ``faces (F, 3)`` shared by both (or a batch's ``(B, F, 3)`` of one topology) -> ``(B, T, V, 3)``,
    bounding-box centred, in the driving dtype."""
    B, T, V, _ = driving.shape
    if target.shape[-2] != V:
        raise ValueError(f"deformation transfer needs driver and target of one topology; got {V} and "
                         f"{target.shape[-2]} vertices")
    faces = (faces[0] if faces.dim() == 3 else faces).detach().to("cpu", torch.int64).contiguous()
    i, j, factor = _topology(faces.numpy().tobytes(), len(faces), V)
    device = driving.device
    i, j = i.to(device), j.to(device)
    x = target.detach().double()[:, None].expand(B, T, V, 3)
    rotation = _rotations(x, driving.detach().double(), i, j)
    source_edges = x[..., j, :] - x[..., i, :]
    turned = 0.5 * ((rotation[..., i, :, :] + rotation[..., j, :, :]) @ source_edges[..., None])[..., 0]
    rhs = torch.zeros(B, T, V, 3, dtype=torch.float64, device=device)
    rhs.index_add_(2, i, -turned).index_add_(2, j, turned)
    columns = rhs.permute(2, 0, 1, 3).reshape(V, B * T * 3).cpu().numpy()  # one solve for every frame and axis
    # SuperLU's per-column BLAS calls on one thread: OpenBLAS's threads spinning beside torch's took 16 ms, not 1.2
    with _THREADPOOLS.limit(limits=1, user_api="blas"):
        solution = factor.solve(columns)
    y = torch.from_numpy(solution).reshape(V, B, T, 3).permute(1, 2, 0, 3).to(device)
    y = y - (y.amin(dim=2, keepdim=True) + y.amax(dim=2, keepdim=True)) / 2
    return y.to(driving.dtype)
