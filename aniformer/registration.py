"""Anny's body fitted onto any mesh in any orientation and pose (``fit_template``), and the axis a mesh's
body stands along (``detect_up``): the fit ``aniformer.correspondence`` carries motion across with.

The fit: Anny's phenotype (build), its 104 bone rotations and a global orientation, then small smooth
per-vertex offsets, minimising the symmetric Chamfer distance between the two surfaces (oriented: points
match points whose normals face their way). Characters come in any orientation and pose, so many
hypotheses start at once on a coarse template: every rotation of a cube (SO(3) within 63 degrees) from
Anny's rest pose, and pose seeds turned onto the mesh by its geodesic extremities (head, hands, feet: the
same in any pose), each template vertex pulled towards the mesh vertex of the nearest geodesic
coordinates, for each of the four ways the hands and feet can be left or right.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import functools
import hashlib
import importlib.metadata
import inspect
import itertools
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import roma
import scipy.spatial
import torch
import trimesh

from aniformer.geometry import STANDS_ALONG
from aniformer.io.files import atomic_path
from aniformer.surface import (
    GeodesicFrame,
    OrientedCloud,
    chamfer,
    extremities,
    geodesic_frame,
    nearest_pairs,
    normals,
    surface_parts,
)
from aniformer.transfer import mesh_edges

COARSE_TOPOLOGY = "notoes_collapse3pc"  # every hypothesis is tried here first: Anny's rig is one for all topologies
POSE_SEEDS = 6  # rest plus body poses each orientation hypothesis starts from (sitting, crouching, striding...)
KEEP = 8  # hypotheses refined at the template topology after the coarse round
COARSE_TEMPLATE_SAMPLES = 500
COARSE_MESH_POINTS = 1500
TEMPLATE_SAMPLES = 2000  # points on the template surface per Chamfer evaluation
MESH_SAMPLES = 3000  # points on the mesh surface, besides its vertices (without them: 2x the error)
FIT_THREADS = 2  # the fit's hypotheses side by side
MESH_VERTICES = 3000  # of a larger mesh's vertices, a fixed random subset: the fit's time stays flat in the vertex count
SIDES = np.array([[0, a, 3 - a, b, 7 - b] for a in (1, 2) for b in (3, 4)])  # which hand and foot is which
PARTNER_WEIGHT = (1.0, 0.1)  # of the geodesic partners' robust distance in the loss: coarse round, refinement
PARTNER_SCALE = 0.1  # metres: partners farther apart than this pull less (a robust, Geman-McClure distance)
COARSE_LR = 0.03  # measured: 0.06 sends rest-pose bodies to wrong basins (6-9 cm off instead of 0.6)
PREFIT_STEPS = 100  # of the pose seeds pulled to their geodesic partners alone, before any Chamfer step
PREFIT_LR = 0.05
# (step, rows going on) of the coarse round and the refinement, from the loss curves of 32 posed validation
# bodies: 24 rows at coarse step 16 already held all 8 finalists, 3 at refinement step 60 the winner; a margin here
COARSE_PRUNE = (20, 24)
REFINE_PRUNE = (60, 4)
NEIGHBOURS_EVERY = 2  # Chamfer steps per nearest-neighbour search (the searches were a third of the fit's time)
PROP_SHARE = 0.15  # of the surface: separate parts up to this together may lie off the body (a sword, long hair)
POSE_PRIOR = 1e-4  # per rad^2 of bone rotation: keeps unconstrained bones (fingers, face) at rest
CACHE_ENV = "ANIFORMER_CACHE_DIR"  # where fits are kept (``fit_cache_dir``)


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


class AnnyTemplate:
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
        rest = self.rest(phenotype)
        return self.model.get_skinned_vertices(rest["rest_vertices"], self._skeleton(rest, rotvecs))

    def rest(self, phenotype: torch.Tensor) -> dict:
        """Anny's rest body of ``phenotype (B, 6)``: its vertices and bones."""
        # not Anny's ``forward``: it would also pose and skin the body at identity, unused here (~13% of a fit step)
        _, phenotype, local_changes, face_expression = self.model.get_tensor_inputs(None, phenotype, None, None)
        return self.model.get_rest_model(self.model._get_phenotype_blendshape_coefficients(phenotype, local_changes,
                                                                                            face_expression))

    def _skeleton(self, rest: dict, rotvecs: torch.Tensor) -> torch.Tensor:
        """The ``rest`` body's bones' transforms ``(B, bones, 4, 4)`` in ``rotvecs``."""
        deltas = torch.eye(4).repeat(len(rotvecs), self.bones, 1, 1)
        deltas = torch.cat([torch.cat([roma.rotvec_to_rotmat(rotvecs), deltas[..., :3, 3:]], -1), deltas[..., 3:, :]], -2)
        transforms, _ = self.model.get_bone_transforms(deltas, rest["rest_bone_poses"])
        return transforms

    def vertex_transforms(self, phenotype: torch.Tensor, rotvecs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(rest vertices ``(B, V, 3)``, each vertex's skinning transform ``(B, V, 4, 4)``: its bones' transforms
        blended by its weights, what linear blend skinning moves it by)."""
        rest = self.rest(phenotype)
        weights, bones = self.model.vertex_bone_weights, self.model.vertex_bone_indices
        blended = (weights[None, ..., None, None] * self._skeleton(rest, rotvecs)[:, bones]).sum(2)
        return rest["rest_vertices"], blended

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
def anny_template(topology: str, samples: int = TEMPLATE_SAMPLES) -> AnnyTemplate:
    """The ``AnnyTemplate`` of ``topology``, built once per topology and sample count."""
    return AnnyTemplate(topology, samples)


def _fit_body(template: AnnyTemplate, cloud: OrientedCloud, start: list[torch.Tensor], steps: range, total: int,
              partners: torch.Tensor, weights: torch.Tensor, lr: float, moments: list[dict] | None = None):
    """Adam on (phenotype logits, bone rotations, shift) of each batch row from ``start`` (with Adam's
    ``moments`` of an earlier part of the round, if any), over ``steps`` of a round of ``total``, pulling each
    template vertex to its geodesic partner on the mesh (``partners (B, V_a, 3)``) with ``weights (B,)``:
    (the parameters, the posed vertices, the Chamfer loss per row: what hypotheses are compared by, Adam's
    moments)."""
    phenotype, rotvecs, shift = params = [p.detach().clone().requires_grad_(True) for p in start]
    optimiser = torch.optim.Adam(params, lr=lr)
    for p, state in zip(params, moments or []):
        optimiser.state[p] = state
    for step in steps:
        posed = template.vertices(torch.sigmoid(phenotype), rotvecs)
        posed = posed - (posed.amin(1, keepdim=True) + posed.amax(1, keepdim=True)) / 2 + shift
        prior = POSE_PRIOR * rotvecs[:, 1:].square().sum((1, 2))
        fit = prior
        if cloud is not None:
            points, point_normals = template.samples(posed)
            # a part's first step has no neighbours yet; the round's last step's loss ranks the hypotheses
            if step % NEIGHBOURS_EVERY == 0 or step == steps.start or step == total - 1:
                nearest = nearest_pairs(points, point_normals, cloud)
            fit = fit + chamfer(points, cloud, nearest)
        apart = (posed - partners).square().sum(-1)
        pulled = weights * PARTNER_SCALE**2 * (apart / (apart + PARTNER_SCALE**2)).mean(1)
        optimiser.zero_grad()
        (fit + pulled).sum().backward()
        optimiser.step()
    return params, posed.detach(), fit.detach(), [optimiser.state[p] for p in params]


def _fit_bodies(template: AnnyTemplate, cloud: OrientedCloud, start: list[torch.Tensor], steps: int,
                partners: torch.Tensor, weights: torch.Tensor, lr: float = 0.03,
                prune: tuple[int, int] | None = None):
    """``_fit_body`` with the rows split over ``FIT_THREADS`` threads: the rows are independent (a summed loss,
    Adam per element), and the k-d tree searches and tensor ops release the GIL. ``prune (step, keep)``: at
    ``step`` only the ``keep`` rows of least loss go on, as they would have (successive halving). (the
    parameters, posed vertices and loss of the rows that went on, those rows' indices)."""
    rows, params, moments, loss = torch.arange(len(start[0])), start, None, None
    for part in [range(steps)] if prune is None or prune[0] >= steps else [range(prune[0]), range(prune[0], steps)]:
        if part.start:
            going_on = loss.argsort()[: prune[1]]
            rows, params, moments = rows[going_on], [p[going_on] for p in params], _moment_rows(moments, going_on)
        chunks = [torch.from_numpy(c) for c in np.array_split(np.arange(len(rows)), FIT_THREADS) if len(c)]

        def fit(chunk, part=part, params=params, moments=moments, rows=rows):
            with torch.enable_grad():  # grad mode is per thread
                return _fit_body(template, cloud, [p[chunk] for p in params], part, steps, partners[rows[chunk]],
                                 weights[rows[chunk]], lr, moments and _moment_rows(moments, chunk))

        with concurrent.futures.ThreadPoolExecutor(len(chunks)) as pool:
            results = list(pool.map(fit, chunks))
        params, posed, loss = ([torch.cat(k) for k in zip(*(r[0] for r in results))],
                               torch.cat([r[1] for r in results]), torch.cat([r[2] for r in results]))
        moments = [{k: torch.cat([r[3][i][k] for r in results]) if v.dim() else v for k, v in results[0][3][i].items()}
                   for i in range(len(params))]
    return [p.detach() for p in params], posed, loss, rows


def _moment_rows(moments: list[dict], rows: torch.Tensor) -> list[dict]:
    """Adam's per-parameter state for a subset of the batch rows (its step count copied: each optimiser counts its own)."""
    return [{k: v[rows] if v.dim() else v.clone() for k, v in state.items()} for state in moments]


def kabsch(source: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """``(B, 3, 3)``: the rotations best turning centred ``source (B, K, 3)`` onto centred ``target (B, K, 3)``."""
    source, target = source - source.mean(1, keepdim=True), target - target.mean(1, keepdim=True)
    return roma.special_procrustes(target.transpose(1, 2) @ source)


@contextlib.contextmanager
def one_thread():
    """Run a fit's many small tensor ops on one thread: with two threads on a busy 2-core machine each
    step was measured 60x slower (threads waiting on each other), and idle it is no faster (the
    registration's fit here, the rig's in ``aniformer.rig`` and ``aniformer.rig_motion``)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


@dataclass(frozen=True)
class BodyFit:
    """Anny fitted onto a mesh: the template's vertices in the mesh's coordinates, the fitted body's
    height at rest (metres of the mesh), the symmetric Chamfer loss of the pose fit, and per template
    vertex the inverse of its skinning in the fitted pose (``unposed``)."""

    vertices: np.ndarray  # (V_a, 3) float32
    height: float
    loss: float
    to_rest: np.ndarray  # (V_a, 3, 4) per template vertex: the inverse of its skinning, mesh coordinates to Anny's rest pose

    def unposed(self, points: np.ndarray) -> np.ndarray:
        """``points (V_a, 3)``, one near each template vertex (the template on the mesh), moved to Anny's rest pose
        by the inverse of that vertex's skinning in the fitted pose."""
        return (self.to_rest[..., :3] @ points[..., None])[..., 0] + self.to_rest[..., 3]


@one_thread()  # all of it: the fit's basin depends on the last bits of its start (a box: other fits on 2 threads than on 1, 3, 4)
def fit_template(vertices: np.ndarray, faces: np.ndarray, topology: str, *,
                 steps: tuple[int, int, int] = (50, 300, 100), orientations: torch.Tensor | None = None,
                 seed: int = 0) -> BodyFit:
    """Anny at ``topology`` fitted onto a mesh in any orientation and pose (see ``BodyFit``).

    On the coarse template: each pose seed turned onto the mesh's geodesic partners, for each
    assignment of hands and feet (``SIDES``), and the rest pose in each of ``orientations`` (default:
    ``orientation_hypotheses``). The ``KEEP`` of least Chamfer distance go on at ``topology``, and
    the best of them gets small smooth per-vertex offsets. The body covers the mesh's largest connected
    surface; separate parts up to ``PROP_SHARE`` of the surface (eyeballs, a sword) only attract it.
    ``steps``: of the coarse round, of the kept ones (300, not 110: 0.8x the template error on validation
    bodies, 1.56x the time; docs/results.md), of the offsets."""
    mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), faces, process=False)
    centre = (mesh.bounds[0] + mesh.bounds[1]) / 2
    samples, sample_faces = trimesh.sample.sample_surface(mesh, MESH_SAMPLES, seed=seed)
    vertex_normals, face_normals = normals(mesh.vertices, mesh.faces)
    outward = np.sign(((mesh.triangles_center - centre) * face_normals * mesh.area_faces[:, None]).sum()) or 1.0
    shown = np.sort(np.random.default_rng(seed).permutation(len(mesh.vertices))[:MESH_VERTICES])
    parts, shares = surface_parts(mesh.vertices, faces)
    # the body is fitted to cover its largest surface; separate small parts (eyeballs, a hat, a sword) only attract it
    covered = parts == 0 if shares[1:].sum() <= PROP_SHARE else np.ones(len(parts), bool)
    cloud = OrientedCloud.of(np.concatenate([samples, mesh.vertices[shown]]) - centre,
                             outward * np.concatenate([face_normals[sample_faces], vertex_normals[shown]]),  # inward-wound too
                             None if covered.all() else np.concatenate([covered[faces[sample_faces, 0]], covered[shown]]))
    coarse_cloud = cloud.subset(np.random.default_rng(seed).permutation(len(cloud.oriented))[:COARSE_MESH_POINTS])
    coarse, template = anny_template(COARSE_TOPOLOGY, COARSE_TEMPLATE_SAMPLES), anny_template(topology)
    root = template.bone_labels.index("root")
    seeds = pose_seeds(template.bone_labels)
    frame = geodesic_frame(mesh.vertices, faces)
    partners = torch.from_numpy(_dense_targets(coarse.geodesic.coordinates, frame, mesh.vertices - centre, SIDES)).float()
    with torch.no_grad():
        seed_bodies = coarse.vertices(torch.full((len(seeds), 6), 0.5), seeds)
    turns = kabsch(seed_bodies.repeat_interleave(len(SIDES), 0), partners.repeat(len(seeds), 1, 1))
    if orientations is None:  # plain hypotheses too, for bodies whose extremities are not five limbs' ends
        orientations = orientation_hypotheses()
    rotvecs = torch.cat([seeds.repeat_interleave(len(SIDES), 0), seeds[:1].repeat(len(orientations), 1, 1)])
    rotvecs[:, root] = roma.rotmat_to_rotvec(torch.cat([turns, orientations]))
    side = torch.cat([torch.arange(len(SIDES)).repeat(len(seeds)), torch.zeros(len(orientations), dtype=torch.long)])
    weights = torch.cat([torch.ones(len(seeds) * len(SIDES)), torch.zeros(len(orientations))])
    start = [torch.zeros(len(rotvecs), 6), rotvecs, torch.zeros(len(rotvecs), 1, 3)]  # logit 0: Anny's average
    with torch.enable_grad():
        # posed bodies: the skeleton bent onto the partners first (cheap: no nearest-neighbour search), so the
        # Chamfer round starts in the right basin (posed validation bodies: 7.5 -> 2.1 cm mean error)
        posed_rows = len(seeds) * len(SIDES)  # the orientation rows have no partners to be pulled to
        prefit, _, _, _ = _fit_bodies(coarse, None, [p[:posed_rows] for p in start], PREFIT_STEPS,
                                   partners[side[:posed_rows]], weights[:posed_rows], lr=PREFIT_LR)
        start = [torch.cat([fitted, p[posed_rows:]]) for fitted, p in zip(prefit, start)]
        params, _, loss, rows = _fit_bodies(coarse, coarse_cloud, start, steps[0], partners[side],
                                            PARTNER_WEIGHT[0] * weights, lr=COARSE_LR, prune=COARSE_PRUNE)
        kept = loss.argsort()[:KEEP]
        params, kept = [p[kept] for p in params], rows[kept]
        partners = torch.from_numpy(_dense_targets(template.geodesic.coordinates, frame, mesh.vertices - centre,
                                                   SIDES)).float()
        params, posed, loss, _ = _fit_bodies(template, cloud, params, steps[1], partners[side[kept]],
                                             PARTNER_WEIGHT[1] * weights[kept], prune=REFINE_PRUNE)
        best = int(loss.argmin())
        posed = posed[best : best + 1]
        offsets = torch.zeros_like(posed, requires_grad=True)
        i, j = (torch.from_numpy(e) for e in mesh_edges(template.faces, posed.shape[1]))
        optimiser = torch.optim.Adam([offsets], lr=2e-3)
        for _ in range(steps[2]):  # small smooth offsets: what the body model's shape space misses
            smooth = (offsets[:, i] - offsets[:, j]).square().sum(-1).mean()
            points, point_normals = template.samples(posed + offsets)
            fit = chamfer(points, cloud, nearest_pairs(points, point_normals, cloud))
            optimiser.zero_grad()
            (fit + 10.0 * smooth).backward()
            optimiser.step()
        rest, skinning = template.vertex_transforms(torch.sigmoid(params[0][best : best + 1]).expand(2, -1),
                                                    torch.cat([params[1][best : best + 1], torch.zeros(1, template.bones, 3)]))
        rest, (fitted, standing) = rest[0].detach().double(), skinning.detach().double()  # the fitted pose, the rest pose
    at_rest = (standing[:, :3, :3] @ rest[..., None])[..., 0] + standing[:, :3, 3]  # Anny's rest pose: no rotation
    height = float(at_rest[:, 2].amax() - at_rest[:, 2].amin())
    # per vertex: the fit's placement of the skinned body (its centring, the fitted shift, the mesh's centre)
    placed = posed[0].double() - (fitted[:, :3, :3] @ rest[..., None])[..., 0] - fitted[:, :3, 3] + torch.from_numpy(centre)
    unskin = torch.linalg.pinv(fitted[:, :3, :3])  # a blend of two rotations 180 degrees apart is singular
    to_rest = torch.cat([standing[:, :3, :3] @ unskin, (standing[:, :3, 3:] - standing[:, :3, :3] @ unskin
                                                        @ (fitted[:, :3, 3] + placed)[..., None])], -1)
    return BodyFit(((posed + offsets).detach()[0].numpy() + centre).astype(np.float32), height, float(fit.detach()),
                   to_rest.numpy())


_fit_defaults = {name: p.default for name, p in inspect.signature(fit_template).parameters.items()
                 if p.default is not inspect.Parameter.empty}


def fit_cache_dir() -> Path:
    """Where ``cached_fit`` keeps fits: ``$ANIFORMER_CACHE_DIR``, else ``$XDG_CACHE_HOME/aniformer``, else
    ``~/.cache/aniformer`` (beside Anny's own build cache, ``~/.cache/anny``)."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV])
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "aniformer"


@functools.cache
def _fit_code_version() -> bytes:
    """A digest of everything a fit depends on besides its inputs: every source file of this package (so any
    code change refits) and the versions of the libraries it runs on."""
    digest = hashlib.sha256()
    for source in sorted(Path(__file__).resolve().parent.rglob("*.py")):
        digest.update(source.read_bytes())
    for library in ("anny", "torch", "numpy", "scipy", "trimesh", "roma"):
        digest.update(f"{library}=={importlib.metadata.version(library)};".encode())
    return digest.digest()


def _fit_key(vertices: np.ndarray, faces: np.ndarray, topology: str, options: dict) -> str:
    options = {name: value for name, value in options.items()  # an option given at its default fits the same
               if name not in _fit_defaults or repr(np.asarray(value).tolist()) != repr(np.asarray(_fit_defaults[name]).tolist())}
    digest = hashlib.sha256(_fit_code_version())
    settings = {name: value for name, value in globals().items() if name.isupper()}  # as set now: a changed one refits
    digest.update(repr(sorted(settings.items(), key=lambda item: item[0])).encode())
    for part in (np.asarray(vertices, np.float32), np.asarray(faces, np.int64), topology,
                 *(item for name in sorted(options) for item in (name, np.asarray(options[name])))):
        array = np.ascontiguousarray(part) if isinstance(part, np.ndarray) else np.frombuffer(part.encode(), np.uint8)
        digest.update(f"{array.dtype}{array.shape}".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


def cached_fit(vertices: np.ndarray, faces: np.ndarray, topology: str, **options) -> tuple[BodyFit, bool]:
    """``fit_template``'s fit of this mesh, loaded from ``fit_cache_dir`` if this code fitted the same mesh
    (its vertices, faces, topology and ``options``) before, else fitted and kept there: (the fit, whether it
    was loaded). The fit is deterministic, so a kept one is the same bytes a new fit would be; a character
    animated with clip after clip is registered once (24 s at 18k vertices on 2 cores)."""
    path = fit_cache_dir() / "registrations" / f"{_fit_key(vertices, faces, topology, options)}.npz"
    try:
        with np.load(path, allow_pickle=False) as kept:
            return BodyFit(kept["vertices"], float(kept["height"]), float(kept["loss"]), kept["to_rest"]), True
    except (OSError, ValueError, KeyError, zipfile.BadZipFile):  # none kept, or a damaged file: fit anew
        pass
    fit = fit_template(vertices, faces, topology, **options)
    with contextlib.suppress(OSError), atomic_path(path) as tmp, open(tmp, "wb") as file:  # read-only, full: no harm
        np.savez(file, vertices=fit.vertices, height=fit.height, loss=fit.loss, to_rest=fit.to_rest)
    return fit, False


def body_axis(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``(3,)``: the unit direction from a body's feet to its head (``aniformer.surface.extremities``)."""
    regions = extremities(np.asarray(vertices, np.float64), faces)
    axis = vertices[regions[0]].mean(0) - np.concatenate([vertices[r] for r in regions[3:]]).mean(0)
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
        return standing, STANDS_ALONG.format(standing)
    return convention, "the format's convention: the body does not stand along y or z"
