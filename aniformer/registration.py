"""Correspondence between any mesh and an Anny topology, so the model can animate any target.

The model works on one topology with vertex correspondence between driver and target (vertex
``i`` is the same body point in both; ``aniformer/transfer.py``). A user's character has its own
vertex count, order and connectivity. ``Correspondence`` fits Anny's body at the model's topology onto
the mesh and keeps the two embeddings that carry motion across:

1. *fit*: Anny's phenotype (build), its 104 bone rotations and a global orientation, then small
   smooth per-vertex offsets, minimising the symmetric Chamfer distance between the two surfaces
   (oriented: points match points whose normals face their way). Characters come in any
   orientation and pose, so many hypotheses start at once on a coarse template (``fit_template``):
   every rotation of a cube (SO(3) within 63 degrees) from Anny's rest pose, and pose seeds turned
   onto the mesh by its geodesic extremities (head, hands, feet: the same in any pose), each
   template vertex pulled towards the mesh vertex of the nearest geodesic coordinates, for each
   of the four ways the hands and feet can be left or right;
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

import concurrent.futures
import contextlib
import functools
import itertools
from dataclasses import dataclass

import numpy as np
import roma
import scipy.sparse
import scipy.sparse.csgraph
import scipy.spatial
import torch
import trimesh

from aniformer.transfer import mesh_edges, vertex_rotations

COARSE_TOPOLOGY = "notoes_collapse3pc"  # every hypothesis is tried here first: Anny's rig is one for all topologies
POSE_SEEDS = 6  # rest plus body poses each orientation hypothesis starts from (sitting, crouching, striding...)
KEEP = 8  # hypotheses refined at the template topology after the coarse round
COARSE_TEMPLATE_SAMPLES = 500
COARSE_MESH_POINTS = 1500
TEMPLATE_SAMPLES = 2000  # points on the template surface per Chamfer evaluation
MESH_SAMPLES = 3000  # points on the mesh surface, besides its vertices (without them: 2x the error)
FIT_THREADS = 2  # the fit's hypotheses side by side
MESH_VERTICES = 3000  # of a larger mesh's vertices, a fixed random subset: the fit's time stays flat in the vertex count
EXTREMITY_RADIUS = 0.08  # of the head-to-foot geodesic distance: a hand or a foot, not the fingertip alone
SIDES = np.array([[0, a, 3 - a, b, 7 - b] for a in (1, 2) for b in (3, 4)])  # which hand and foot is which
PARTNER_WEIGHT = (1.0, 0.1)  # of the geodesic partners' robust distance in the loss: coarse round, refinement
PARTNER_SCALE = 0.1  # metres: partners farther apart than this pull less (a robust, Geman-McClure distance)
COARSE_LR = 0.03  # measured: 0.06 sends rest-pose bodies to wrong basins (6-9 cm off instead of 0.6)
NORMAL_WEIGHT = 0.05  # metres per unit of normal difference in the Chamfer matches: opposite normals cost 10 cm
PREFIT_STEPS = 100  # of the pose seeds pulled to their geodesic partners alone, before any Chamfer step
PREFIT_LR = 0.05
NEIGHBOURS_EVERY = 2  # Chamfer steps per nearest-neighbour search (the searches were a third of the fit's time)
POSE_PRIOR = 1e-4  # per rad^2 of bone rotation: keeps unconstrained bones (fingers, face) at rest


def orientation_hypotheses() -> torch.Tensor:
    """``(24, 3, 3)``: the rotations of a cube onto itself; every rotation is within 63 degrees of one,
    close enough for the fit to turn the rest of the way (upright, lying, upside down, any heading)."""
    mats = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            m = np.zeros((3, 3))
            m[range(3), perm] = signs
            if np.linalg.det(m) > 0:
                mats.append(m)
    return torch.from_numpy(np.stack(mats)).float()


@functools.cache
def pose_seeds(bone_labels: tuple[str, ...]) -> torch.Tensor:
    """``(POSE_SEEDS, bones, 3)``: Anny's rest pose and body poses of the stream's families at a fixed
    seed of their own (no test pose), each at the root's rest orientation."""
    from aniformer.synth.poses import sample_windows

    families = ("crouch", "random", "locomotion", "bend", "kick")[: POSE_SEEDS - 1]
    rngs = [np.random.default_rng([7, k]) for k in range(len(families))]
    rotvecs, _ = sample_windows(families, ["upright"] * len(families), rngs, 1, bone_labels)
    rotvecs = torch.from_numpy(rotvecs[:, 0])
    rotvecs[:, bone_labels.index("root")] = 0.0
    return torch.cat([torch.zeros(1, *rotvecs.shape[1:]), rotvecs])


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


def _edge_graph(vertices: np.ndarray, faces: np.ndarray) -> scipy.sparse.csr_matrix:
    i, j = mesh_edges(faces, len(vertices))
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
    """The extremities of a body's largest connected surface, labelled. The four limb ends are the first
    four samples of farthest-point sampling of geodesic distance (hands and feet are far apart from each
    other; the head is not the fifth: a belly point was measured a few millimetres farther from the
    limbs than the crown). The head is the vertex, and the hands the pair of limb ends, that make it
    nearest both hands alike and farthest from both feet alike. Each region is the vertices within
    ``EXTREMITY_RADIUS`` of the head-to-foot distance of its point."""
    graph = _edge_graph(np.asarray(vertices, np.float64), faces)
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
    regions = [np.flatnonzero(distances[k] < EXTREMITY_RADIUS * scale) for k in (-1, *hands, *feet)]
    coordinates = np.stack([scipy.sparse.csgraph.dijkstra(graph, directed=False, indices=r, min_only=True)
                            for r in regions], 1) / scale
    return GeodesicFrame(regions, coordinates)


def _dense_targets(template_coordinates: np.ndarray, frame: GeodesicFrame, vertices: np.ndarray,
                   sides: np.ndarray) -> np.ndarray:
    """``(len(sides), V_a, 3)``: per assignment of the mesh's hands and feet to the template's (a row of
    ``sides``), each template vertex's partner on the mesh: the body vertex of the nearest geodesic
    coordinates."""
    body = np.flatnonzero(np.isfinite(frame.coordinates).all(1))
    targets = []
    for order in sides:
        _, nearest = scipy.spatial.cKDTree(frame.coordinates[body][:, order]).query(template_coordinates)
        targets.append(vertices[body[nearest]])
    return np.stack(targets)


@dataclass(frozen=True)
class _Cloud:
    """Points on a mesh with their outward normals, and a k-d tree of both (``NORMAL_WEIGHT``)."""

    points: torch.Tensor  # (M, 3)
    oriented: np.ndarray  # (M, 6): points and weighted normals
    tree: scipy.spatial.cKDTree

    @classmethod
    def of(cls, points: np.ndarray, normals: np.ndarray) -> _Cloud:
        oriented = np.concatenate([points, NORMAL_WEIGHT * normals], 1)
        return cls(torch.from_numpy(points).float(), oriented, scipy.spatial.cKDTree(oriented))

    def subset(self, index: np.ndarray) -> _Cloud:
        return _Cloud.of(self.points.numpy()[index], self.oriented[index, 3:] / NORMAL_WEIGHT)


def _nearest(a: torch.Tensor, a_normals: np.ndarray, b: _Cloud) -> tuple[torch.Tensor, torch.Tensor]:
    """(each point of ``a (B, N, 3)``'s nearest in the cloud ``(B, N)``, each cloud point's nearest in ``a``
    ``(B, M)``), matched by k-d trees of points and normals (``normals (B, N, 3)``): a point matches a
    point of the surface facing its way, so a front is not fitted onto a back."""
    oriented = np.concatenate([a.detach().numpy(), NORMAL_WEIGHT * a_normals], -1)
    nearest_b = torch.from_numpy(np.stack([b.tree.query(p)[1] for p in oriented]))
    nearest_a = torch.from_numpy(np.stack([scipy.spatial.cKDTree(p).query(b.oriented)[1] for p in oriented]))
    return nearest_b, nearest_a


def _chamfer(a: torch.Tensor, b: _Cloud, nearest: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
    """Symmetric squared Chamfer distance per batch row between ``a (B, N, 3)`` and a cloud -> ``(B,)``,
    over the ``_nearest`` pairs: only the distances are differentiated (a dense distance matrix costs
    ~1 s per step)."""
    nearest_b, nearest_a = nearest
    to_b = (a - b.points[nearest_b]).square().sum(-1).mean(1)
    to_a = (b.points[None] - torch.gather(a, 1, nearest_a[..., None].expand(-1, -1, 3))).square().sum(-1).mean(1)
    return to_b + to_a


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


class _Template:
    """Anny at one topology as a differentiable function of (phenotype, bone rotations)."""

    def __init__(self, topology: str, samples: int = TEMPLATE_SAMPLES):
        from aniformer.synth.bodies import BodyModel

        body = BodyModel(topology)
        self.model, self.faces, self.bones = body._model, body.faces, len(body.bone_labels)
        self.bone_labels = tuple(body.bone_labels)
        rng = np.random.default_rng(0)  # fixed sample layout: the fit is deterministic
        self.sample_face_index = rng.integers(0, len(self.faces), samples)
        self.sample_faces = torch.from_numpy(self.faces[self.sample_face_index])
        weights = rng.dirichlet(np.ones(3), samples)
        self.sample_weights = torch.from_numpy(weights.astype(np.float32))

    def vertices(self, phenotype: torch.Tensor, rotvecs: torch.Tensor) -> torch.Tensor:
        rest = self.model(phenotype_kwargs=phenotype)
        deltas = torch.eye(4).repeat(len(rotvecs), self.bones, 1, 1)
        deltas = torch.cat([torch.cat([roma.rotvec_to_rotmat(rotvecs), deltas[..., :3, 3:]], -1), deltas[..., 3:, :]], -2)
        transforms, _ = self.model.get_bone_transforms(deltas, rest["rest_bone_poses"])
        return self.model.get_skinned_vertices(rest["rest_vertices"], transforms)

    @functools.cached_property
    def geodesic(self) -> GeodesicFrame:
        """The geodesic frame of Anny's average body at rest."""
        with torch.no_grad():
            rest = self.vertices(torch.full((1, 6), 0.5), torch.zeros(1, self.bones, 3))[0].numpy()
        return geodesic_frame(rest, self.faces)

    def samples(self, vertices: torch.Tensor) -> tuple[torch.Tensor, np.ndarray]:
        """(the vertices and the surface samples ``(B, V + S, 3)``, their normals ``(B, V + S, 3)`` without grad)."""
        points = torch.cat([vertices, (vertices[:, self.sample_faces] * self.sample_weights[..., None]).sum(2)], 1)
        vertex_normals, face_normals = normals(vertices.detach().numpy(), self.faces)
        return points, np.concatenate([vertex_normals, face_normals[:, self.sample_face_index]], 1)


@functools.cache
def _template(topology: str, samples: int = TEMPLATE_SAMPLES) -> _Template:
    return _Template(topology, samples)


def _fit_body(template: _Template, cloud: _Cloud, start: list[torch.Tensor], steps: int,
              partners: torch.Tensor, weights: torch.Tensor, lr: float = 0.03):
    """Adam on (phenotype logits, bone rotations, shift) of each batch row from ``start``, pulling each
    template vertex to its geodesic partner on the mesh (``partners (B, V_a, 3)``) with ``weights (B,)``:
    (the parameters, the posed vertices, the Chamfer loss per row: what hypotheses are compared by)."""
    phenotype, rotvecs, shift = params = [p.detach().clone().requires_grad_(True) for p in start]
    optimiser = torch.optim.Adam(params, lr=lr)
    for step in range(steps):
        posed = template.vertices(torch.sigmoid(phenotype), rotvecs)
        posed = posed - (posed.amin(1, keepdim=True) + posed.amax(1, keepdim=True)) / 2 + shift
        prior = POSE_PRIOR * rotvecs[:, 1:].square().sum((1, 2))
        fit = prior
        if cloud is not None:
            points, point_normals = template.samples(posed)
            if step % NEIGHBOURS_EVERY == 0 or step == steps - 1:  # the last step's loss ranks the hypotheses
                nearest = _nearest(points, point_normals, cloud)
            fit = fit + _chamfer(points, cloud, nearest)
        apart = (posed - partners).square().sum(-1)
        pulled = weights * PARTNER_SCALE**2 * (apart / (apart + PARTNER_SCALE**2)).mean(1)
        optimiser.zero_grad()
        (fit + pulled).sum().backward()
        optimiser.step()
    return params, posed.detach(), fit.detach()


def _fit_bodies(template: _Template, cloud: _Cloud, start: list[torch.Tensor], steps: int,
                partners: torch.Tensor, weights: torch.Tensor, lr: float = 0.03):
    """``_fit_body`` with the rows split over ``FIT_THREADS`` threads: the rows are independent (a summed loss,
    Adam per element), and the k-d tree searches and tensor ops release the GIL."""
    parts = [rows for rows in np.array_split(np.arange(len(start[0])), FIT_THREADS) if len(rows)]

    def fit(rows):
        with torch.enable_grad():  # grad mode is per thread
            return _fit_body(template, cloud, [p[rows] for p in start], steps, partners[rows], weights[rows], lr)

    with concurrent.futures.ThreadPoolExecutor(len(parts)) as pool:
        results = list(pool.map(fit, parts))
    params = [torch.cat([r[0][k] for r in results]) for k in range(len(start))]
    return params, torch.cat([r[1] for r in results]), torch.cat([r[2] for r in results])


def _kabsch(source: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """``(B, 3, 3)``: the rotations best turning centred ``source (B, K, 3)`` onto centred ``target (B, K, 3)``."""
    source, target = source - source.mean(1, keepdim=True), target - target.mean(1, keepdim=True)
    return roma.special_procrustes(target.transpose(1, 2) @ source)


@contextlib.contextmanager
def one_thread():
    """Run a fit's many small tensor ops on one thread: with two threads on a busy 2-core machine each
    step was measured 60x slower (threads waiting on each other), and idle it is no faster (the
    registration's fit here, the rig's in ``aniformer.rig``)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


@dataclass(frozen=True)
class BodyFit:
    """Anny fitted onto a mesh: the template's vertices in the mesh's coordinates, the fitted body's
    height at rest (metres of the mesh) and the symmetric Chamfer loss of the pose fit."""

    vertices: np.ndarray  # (V_a, 3) float32
    height: float
    loss: float


def fit_template(vertices: np.ndarray, faces: np.ndarray, topology: str, *,
                 steps: tuple[int, int, int] = (50, 110, 100), orientations: torch.Tensor | None = None,
                 seed: int = 0) -> BodyFit:
    """Anny at ``topology`` fitted onto a mesh in any orientation and pose (see ``BodyFit``).

    On the coarse template: each pose seed turned onto the mesh's geodesic partners, for each
    assignment of hands and feet (``SIDES``), and the rest pose in each of ``orientations`` (default:
    ``orientation_hypotheses``). The ``KEEP`` of least Chamfer distance go on at ``topology``, and
    the best of them gets small smooth per-vertex offsets. ``steps``: of the coarse round, of the
    kept ones, of the offsets."""
    mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), faces, process=False)
    centre = (mesh.bounds[0] + mesh.bounds[1]) / 2
    samples, sample_faces = trimesh.sample.sample_surface(mesh, MESH_SAMPLES, seed=seed)
    vertex_normals, face_normals = normals(mesh.vertices, mesh.faces)
    outward = np.sign(((mesh.triangles_center - centre) * face_normals * mesh.area_faces[:, None]).sum()) or 1.0
    shown = np.sort(np.random.default_rng(seed).permutation(len(mesh.vertices))[:MESH_VERTICES])
    cloud = _Cloud.of(np.concatenate([samples, mesh.vertices[shown]]) - centre,
                      outward * np.concatenate([face_normals[sample_faces], vertex_normals[shown]]))  # faces wound inwards too
    coarse_cloud = cloud.subset(np.random.default_rng(seed).permutation(len(cloud.oriented))[:COARSE_MESH_POINTS])
    coarse, template = _template(COARSE_TOPOLOGY, COARSE_TEMPLATE_SAMPLES), _template(topology)
    root = template.bone_labels.index("root")
    seeds = pose_seeds(template.bone_labels)
    frame = geodesic_frame(mesh.vertices, faces)
    partners = torch.from_numpy(_dense_targets(coarse.geodesic.coordinates, frame, mesh.vertices - centre, SIDES)).float()
    with torch.no_grad():
        seed_bodies = coarse.vertices(torch.full((len(seeds), 6), 0.5), seeds)
    turns = _kabsch(seed_bodies.repeat_interleave(len(SIDES), 0), partners.repeat(len(seeds), 1, 1))
    if orientations is None:  # plain hypotheses too, for bodies whose extremities are not five limbs' ends
        orientations = orientation_hypotheses()
    rotvecs = torch.cat([seeds.repeat_interleave(len(SIDES), 0), seeds[:1].repeat(len(orientations), 1, 1)])
    rotvecs[:, root] = roma.rotmat_to_rotvec(torch.cat([turns, orientations]))
    side = torch.cat([torch.arange(len(SIDES)).repeat(len(seeds)), torch.zeros(len(orientations), dtype=torch.long)])
    weights = torch.cat([torch.ones(len(seeds) * len(SIDES)), torch.zeros(len(orientations))])
    start = [torch.zeros(len(rotvecs), 6), rotvecs, torch.zeros(len(rotvecs), 1, 3)]  # logit 0: Anny's average
    with torch.enable_grad(), one_thread():
        # posed bodies: the skeleton bent onto the partners first (cheap: no nearest-neighbour search), so the
        # Chamfer round starts in the right basin (posed validation bodies: 7.5 -> 2.1 cm mean error)
        posed_rows = len(seeds) * len(SIDES)  # the orientation rows have no partners to be pulled to
        prefit, _, _ = _fit_bodies(coarse, None, [p[:posed_rows] for p in start], PREFIT_STEPS,
                                   partners[side[:posed_rows]], weights[:posed_rows], lr=PREFIT_LR)
        start = [torch.cat([fitted, p[posed_rows:]]) for fitted, p in zip(prefit, start)]
        params, _, loss = _fit_bodies(coarse, coarse_cloud, start, steps[0],
                                    partners[side], PARTNER_WEIGHT[0] * weights, lr=COARSE_LR)
        kept = loss.argsort()[:KEEP]
        partners = torch.from_numpy(_dense_targets(template.geodesic.coordinates, frame, mesh.vertices - centre,
                                                   SIDES)).float()
        params, posed, loss = _fit_bodies(template, cloud, [p[kept] for p in params], steps[1],
                                        partners[side[kept]], PARTNER_WEIGHT[1] * weights[kept])
        best = int(loss.argmin())
        posed = posed[best : best + 1]
        offsets = torch.zeros_like(posed, requires_grad=True)
        i, j = (torch.from_numpy(e) for e in mesh_edges(template.faces, posed.shape[1]))
        optimiser = torch.optim.Adam([offsets], lr=2e-3)
        for _ in range(steps[2]):  # small smooth offsets: what the body model's shape space misses
            smooth = (offsets[:, i] - offsets[:, j]).square().sum(-1).mean()
            points, point_normals = template.samples(posed + offsets)
            fit = _chamfer(points, cloud, _nearest(points, point_normals, cloud))
            optimiser.zero_grad()
            (fit + 10.0 * smooth).backward()
            optimiser.step()
        rest = template.vertices(torch.sigmoid(params[0][best : best + 1]), torch.zeros(1, template.bones, 3)).detach()
    height = float(rest[0, :, 2].amax() - rest[0, :, 2].amin())
    return BodyFit(((posed + offsets).detach()[0].numpy() + centre).astype(np.float32), height, float(fit.detach()))


def body_axis(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``(3,)``: the unit direction from a body's feet to its head (``geodesic_frame``'s extremities)."""
    frame = geodesic_frame(np.asarray(vertices, np.float64), faces)
    axis = vertices[frame.regions[0]].mean(0) - np.concatenate([vertices[r] for r in frame.regions[3:]]).mean(0)
    return axis / max(float(np.linalg.norm(axis)), 1e-12)


UP_CONE = np.cos(np.radians(35))  # a body whose feet-to-head axis is this close to an axis stands along it


def detect_up(frames: np.ndarray, faces: np.ndarray, convention: str) -> tuple[str, str]:
    """(up axis, why) of meshes ``frames (K, V, 3)`` of one file or clip, ``convention`` the format's
    (glTF: y, the others: z): the axis among z and y that the bodies stand along in most frames, else
    the convention (a lying or crawling body does not say which way is up)."""
    axes = np.stack([body_axis(frame, faces) for frame in frames])
    votes = {up: int((axes @ np.eye(3)[{"z": 2, "y": 1}[up]] > UP_CONE).sum()) for up in ("z", "y")}
    standing = max(votes, key=votes.get)
    if 2 * votes[standing] > len(frames):
        return standing, f"the body stands along {standing}"
    return convention, "the format's convention: the body does not stand along y or z"


class Correspondence:
    """A mesh registered to an Anny topology: read its frames on the template, carry poses back.

    ``template_faces`` is the Anny topology's; ``fitted`` Anny's fitted body (``BodyFit``: given, or
    fitted here with ``fit_options``); ``template`` its vertices snapped onto the mesh's surface;
    ``rms`` the root-mean-square distance of the fitted template's vertices to the mesh's surface and
    of the mesh's vertices to the template's (mesh units). ``aniformer.trust`` says whether to trust it."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, topology: str, fitted: BodyFit | None = None,
                 **fit_options):
        self.vertices = np.asarray(vertices, np.float32)
        self.faces = np.asarray(faces, np.int64)
        self.topology = topology
        self.template_faces = _template(topology).faces
        self.fitted = fitted or fit_template(self.vertices, self.faces, topology, **fit_options)
        self.template_on_mesh = closest_points(self.fitted.vertices, self.vertices, self.faces)
        self.template = self.to_template(self.vertices)
        self.mesh_on_template = closest_points(self.vertices, self.template, self.template_faces)
        back = self.mesh_on_template.on(self.template, self.template_faces)
        self.template_gap = np.linalg.norm(self.fitted.vertices - self.template, axis=1)  # (V_a,) template to mesh
        self.mesh_gap = np.linalg.norm(self.vertices - back, axis=1)  # (N,) mesh to template
        self.rms = float(np.sqrt(np.square(np.concatenate([self.template_gap, self.mesh_gap])).mean()))

    def to_template(self, frames: np.ndarray) -> np.ndarray:
        """Frames ``(..., N, 3)`` of the mesh's topology as ``(..., V_a, 3)`` on Anny's."""
        return self.template_on_mesh.on(frames, self.faces)

    def from_template(self, posed: np.ndarray, chunk: int = 32) -> np.ndarray:
        """The mesh in the poses of ``posed (T, V_a, 3)`` (the template moved) -> ``(T, N, 3)`` float32: each
        vertex rides its template point, its offset from it turned by the template's local rotation there,
        the weighted rotation mean of its face's corners (``chunk`` frames at a time)."""
        rest = torch.from_numpy(self.template.astype(np.float64))
        corner_index = torch.from_numpy(self.template_faces[self.mesh_on_template.face])  # (N, 3)
        weights = torch.from_numpy(self.mesh_on_template.weights).float()
        offset = torch.from_numpy(self.vertices - self.mesh_on_template.on(self.template, self.template_faces)).float()
        out = np.empty((len(posed), len(self.vertices), 3), np.float32)
        for lo in range(0, len(posed), chunk):
            frames = np.asarray(posed[lo : lo + chunk], np.float32)
            rotations = vertex_rotations(rest, torch.from_numpy(frames), self.template_faces)
            turn = weighted_rotation_mean(roma.rotmat_to_unitquat(rotations).float()[:, corner_index], weights)
            moved = roma.quat_action(turn, offset.expand_as(turn[..., :3]), is_normalized=True)
            out[lo : lo + chunk] = self.mesh_on_template.on(frames, self.template_faces) + moved.numpy()
        return out


def weighted_rotation_mean(quaternions: torch.Tensor, weights: torch.Tensor, tolerance: float = 1e-6,
                           max_iterations: int = 50) -> torch.Tensor:
    """The rotation nearest (chordal) to ``sum_k w_k R_k``, of unit quaternions ``(..., K, 4)`` and ``weights
    (..., K)``: the dominant eigenvector of ``sum_k w_k q_k q_k^T`` (Markley et al. 2007), by power iteration
    from the sign-aligned weighted sum until no component moves by ``tolerance``. Rotations as close as a
    triangle's corners converge in 2-3 steps, at a quarter of the time of a 3x3 eigen solve per vertex."""
    aligned = quaternions * torch.where((quaternions * quaternions[..., :1, :]).sum(-1, keepdim=True) < 0, -1.0, 1.0)
    weighted = weights[..., None] * aligned
    mean = torch.nn.functional.normalize(weighted.sum(-2), dim=-1)
    for _ in range(max_iterations):
        previous, mean = mean, torch.nn.functional.normalize(((aligned @ mean[..., None]) * weighted).sum(-2), dim=-1)
        if (mean - previous).abs().max() < tolerance:
            break
    return mean


def register_clip(frames: np.ndarray, faces: np.ndarray, topology: str, candidates: int = 3):
    """A driving clip of a foreign topology registered on the whole clip, not its first frame alone:
    (the ``Correspondence``, its ``aniformer.trust.Trust``).

    Fits on up to ``candidates`` frames spread over the clip (first frame first) and keeps the
    correspondence the self-check trusts most (its own fit, and the stretch of the template read from
    frames over the whole clip); stops at the first one it trusts."""
    from aniformer.trust import Trust, registration_checks, stretch_check

    shown = frames[np.unique(np.linspace(0, len(frames) - 1, min(len(frames), 64)).round().astype(int))]
    best = None
    for k in np.unique(np.linspace(0, len(frames) - 1, candidates).round().astype(int)):
        fit = Correspondence(frames[k], faces, topology)
        trust = Trust((*registration_checks(fit, "driver"),
                       stretch_check(fit.to_template(shown), fit.template, fit.template_faces, "driver on the template")))
        badness = max(c.value / c.limit for c in trust.checks)
        if best is None or badness < best[0]:
            best = (badness, fit, trust)
        if trust.ok:
            break
    return best[1], best[2]
