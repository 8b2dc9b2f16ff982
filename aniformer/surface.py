"""Geometry of triangle-mesh surfaces, for fitting one body's surface onto another's: points on a surface
that stay put in any pose (``SurfacePoints``, ``closest_points``), normals, a body's geodesic frame (its
labelled extremities and every vertex's geodesic distance to them) and oriented point clouds, matched by
nearest neighbours for the Chamfer distance (``aniformer.registration``, ``aniformer.correspondence``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph
import scipy.spatial
import torch
import trimesh

from aniformer.transfer import mesh_edges

EXTREMITY_RADIUS = 0.08  # of the head-to-foot geodesic distance: a hand or a foot, not the fingertip alone
NORMAL_WEIGHT = 0.05  # metres per unit of normal difference in the Chamfer matches: opposite normals cost 10 cm


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
    import igl  # libigl: its AABB tree answers in C++, 4-20x trimesh's r-tree (docs/benchmarks.md)

    vertices, faces = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    corners = vertices[faces]
    # a point on a face of no area has no barycentric weights: such faces are left out, as long as others exist
    kept = np.flatnonzero(trimesh.triangles.area(corners))
    kept = kept if len(kept) else np.arange(len(faces))
    _, face, closest = igl.point_mesh_squared_distance(np.asarray(points, np.float64), vertices, faces[kept])
    face = kept[face]
    with np.errstate(divide="ignore", invalid="ignore"):  # degenerate triangles: NaN, replaced below
        weights = np.nan_to_num(trimesh.triangles.points_to_barycentric(corners[face], closest), nan=1 / 3)
    weights = np.clip(weights, 0.0, 1.0)
    return SurfacePoints(np.asarray(face, np.int64), weights / weights.sum(1, keepdims=True))


def _edge_graph(vertices: np.ndarray, faces: np.ndarray) -> scipy.sparse.csr_matrix:
    """The mesh's edges weighted by length, and its vertices split at UV seams or hard edges (several vertices at
    one position, as glTF exports write them) joined to the first of their position: one place on the surface."""
    i, j = mesh_edges(faces, len(vertices))
    rows = np.ascontiguousarray(vertices + 0.0)  # + 0.0 turns -0.0 into 0.0: one position, one byte pattern
    _, place = np.unique(rows.view(np.dtype((np.void, rows.itemsize * 3))).ravel(), return_inverse=True)
    first = np.empty(place.max() + 1, np.int64)
    first[place[::-1]] = np.arange(len(vertices))[::-1]  # each position's first vertex
    split = np.flatnonzero(first[place] != np.arange(len(vertices)))
    i, j = np.concatenate([i, split]), np.concatenate([j, first[place[split]]])
    lengths = np.linalg.norm(vertices[i] - vertices[j], axis=1) + 1e-12  # 0 would read as no edge
    return scipy.sparse.coo_matrix((lengths, (i, j)), shape=(len(vertices),) * 2).tocsr()


@dataclass(frozen=True)
class GeodesicFrame:
    """A body's five extremities (``regions``: head, hand, hand, foot, foot vertex sets) and every
    vertex's geodesic distance to each, over the head-to-foot distance (``coordinates (V, 5)``; inf
    off the body's largest connected surface). Both are the same in any pose."""

    regions: list[np.ndarray]
    coordinates: np.ndarray


def geodesic_frame(vertices: np.ndarray, faces: np.ndarray) -> GeodesicFrame:
    """The body's labelled extremities (`extremities`) and every vertex's geodesic distances to them."""
    graph = _edge_graph(np.asarray(vertices, np.float64), faces)
    regions, scale = _labelled_extremities(graph, vertices)
    coordinates = np.stack([scipy.sparse.csgraph.dijkstra(graph, directed=False, indices=r, min_only=True)
                            for r in regions], 1) / scale
    return GeodesicFrame(regions, coordinates)


def extremities(vertices: np.ndarray, faces: np.ndarray) -> list[np.ndarray]:
    """A body's five extremities, labelled (``GeodesicFrame.regions``), without every vertex's distances to them."""
    return _labelled_extremities(_edge_graph(np.asarray(vertices, np.float64), faces), vertices)[0]


def _labelled_extremities(graph: scipy.sparse.csr_matrix, vertices: np.ndarray) -> tuple[list[np.ndarray], float]:
    """(regions, the head-to-foot distance) of the body's largest connected surface. The four limb ends are
    the first four samples of farthest-point sampling of geodesic distance (hands and feet are far apart from
    each other; the head is not the fifth: a belly point was measured a few millimetres farther from the limbs
    than the crown). The head is the vertex, and the hands the pair of limb ends, that make it nearest both
    hands alike and farthest from both feet alike. Each region is the vertices within ``EXTREMITY_RADIUS`` of
    the head-to-foot distance of its point."""
    _, component = scipy.sparse.csgraph.connected_components(graph, directed=False)
    body = np.flatnonzero(component == np.bincount(component).argmax())
    centre = body[np.linalg.norm(vertices[body] - vertices[body].mean(0), axis=1).argmin()]
    nearest = scipy.sparse.csgraph.dijkstra(graph, directed=False, indices=centre)
    samples, distances = [], []
    for _ in range(4):  # farthest-point sampling: each next point farthest from all before
        samples.append(int(np.nanargmax(np.where(np.isfinite(nearest), nearest, np.nan))))
        distances.append(scipy.sparse.csgraph.dijkstra(graph, directed=False, indices=samples[-1]))
        nearest = np.minimum(nearest, distances[-1]) if len(samples) > 1 else distances[-1]
    limbs = np.nan_to_num(np.stack(distances, 1), posinf=0.0)  # (V, 4): every vertex's distance to the limb ends
    labellings = [(hands, feet) for pairs in ([0, 1, 2, 3], [0, 2, 1, 3], [0, 3, 1, 2])
                  for hands, feet in ((pairs[:2], pairs[2:]), (pairs[2:], pairs[:2]))]

    def headness(hands, feet):  # near both hands alike, far from both feet alike: the crown, not a shoulder or the belly
        return (limbs[:, feet].mean(1) - limbs[:, hands].mean(1) - np.abs(limbs[:, hands[0]] - limbs[:, hands[1]])
                - np.abs(limbs[:, feet[0]] - limbs[:, feet[1]]))

    hands, feet = max(labellings, key=lambda h: headness(*h).max())
    head = int(headness(hands, feet).argmax())
    distances.append(scipy.sparse.csgraph.dijkstra(graph, directed=False, indices=head))
    scale = limbs[head, feet].mean()
    return [np.flatnonzero(distances[k] < EXTREMITY_RADIUS * scale) for k in (-1, *hands, *feet)], scale


def surface_parts(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(each vertex's part ``(V,)``, each part's share of the surface area): the mesh's connected surfaces,
    vertices at one position joined (`_edge_graph`), largest by area first (part 0)."""
    vertices = np.asarray(vertices, np.float64)
    _, labels = scipy.sparse.csgraph.connected_components(_edge_graph(vertices, faces), directed=False)
    area = trimesh.triangles.area(vertices[faces])
    shares = np.bincount(labels[faces[:, 0]], area, minlength=labels.max() + 1) / max(area.sum(), 1e-12)
    order = np.argsort(-shares, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return rank[labels], shares[order]


@dataclass(frozen=True)
class OrientedCloud:
    """Points on a mesh with their outward normals, and a k-d tree of both (``NORMAL_WEIGHT``); ``covers``
    marks the points a fitted surface must come near (``None``: all), the Chamfer distance's way back."""

    points: torch.Tensor  # (M, 3)
    oriented: np.ndarray  # (M, 6): points and weighted normals
    tree: scipy.spatial.cKDTree
    covers: np.ndarray | None = None  # (M,) bool

    @classmethod
    def of(cls, points: np.ndarray, normals: np.ndarray, covers: np.ndarray | None = None) -> OrientedCloud:
        oriented = np.concatenate([points, NORMAL_WEIGHT * normals], 1)
        return cls(torch.from_numpy(points).float(), oriented, scipy.spatial.cKDTree(oriented), covers)

    def subset(self, index: np.ndarray) -> OrientedCloud:
        return OrientedCloud.of(self.points.numpy()[index], self.oriented[index, 3:] / NORMAL_WEIGHT,
                                None if self.covers is None else self.covers[index])


def nearest_pairs(a: torch.Tensor, a_normals: np.ndarray, b: OrientedCloud) -> tuple[torch.Tensor, torch.Tensor]:
    """(each point of ``a (B, N, 3)``'s nearest in the cloud ``(B, N)``, each cloud point's nearest in ``a``
    ``(B, M)``), matched by k-d trees of points and normals (``normals (B, N, 3)``): a point matches a
    point of the surface facing its way, so a front is not fitted onto a back."""
    oriented = np.concatenate([a.detach().numpy(), NORMAL_WEIGHT * a_normals], -1)
    nearest_b = torch.from_numpy(np.stack([b.tree.query(p)[1] for p in oriented]))
    nearest_a = torch.from_numpy(np.stack([scipy.spatial.cKDTree(p).query(b.oriented)[1] for p in oriented]))
    return nearest_b, nearest_a


def chamfer(a: torch.Tensor, b: OrientedCloud, nearest: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
    """Symmetric squared Chamfer distance per batch row between ``a (B, N, 3)`` and a cloud -> ``(B,)``, back
    from the cloud's ``covers`` points only, over the ``nearest_pairs``: only the distances are differentiated
    (a dense distance matrix costs ~1 s per step)."""
    nearest_b, nearest_a = nearest
    to_b = (a - b.points[nearest_b]).square().sum(-1).mean(1)
    to_a = (b.points[None] - torch.gather(a, 1, nearest_a[..., None].expand(-1, -1, 3))).square().sum(-1)
    return to_b + (to_a if b.covers is None else to_a[:, torch.from_numpy(b.covers)]).mean(1)


def normals(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(vertex normals ``(..., V, 3)``, face normals ``(..., F, 3)``) of meshes, unit length."""
    v = torch.from_numpy(np.asarray(vertices, np.float64))
    corners = v[..., torch.from_numpy(faces), :]
    face = torch.linalg.cross(corners[..., 1, :] - corners[..., 0, :], corners[..., 2, :] - corners[..., 0, :])
    vertex = torch.zeros_like(v)
    for k in range(3):  # each vertex: the area-weighted sum of its faces' normals
        vertex.index_add_(v.dim() - 2, torch.from_numpy(faces[:, k]), face)
    unit = [torch.nn.functional.normalize(n, dim=-1).numpy() for n in (vertex, face)]
    return unit[0], unit[1]

