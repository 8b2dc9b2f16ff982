"""Correspondence between any mesh and an Anny topology, so the model can animate any target.

The model works on one topology with vertex correspondence between driver and target (vertex
``i`` is the same body point in both; ``aniformer/transfer.py``). A user's character has its own
vertex count, order and connectivity. ``Correspondence`` fits Anny's body at the model's topology onto
the mesh and keeps the two embeddings that carry motion across:

1. *fit*: Anny's build, pose and orientation, then small smooth per-vertex offsets, fitted onto the
   mesh's surface from many hypotheses at once (``aniformer.registration.fit_template``);
2. *template on mesh*: each fitted template vertex snapped to its closest point on the mesh
   (a face and barycentric weights), so ``to_template`` reads any frame of the mesh's topology
   on Anny's (a driving sequence keeps its topology, so one fit serves every frame);
3. *mesh on template*: each mesh vertex's closest point on the template and its offset from it,
   so ``from_template`` carries a posed template back: the vertex rides its point, and its offset
   turns with the template's rotation there (the one-ring rotations of the face's corners,
   blended). Solving for the mesh's own edges turned by those rotations (as-rigid-as-possible)
   was measured worse: 1.3-7.1 against 1.0-1.2 PMD of carry-back error (docs/results.md);
4. *unposed template*: the template on the mesh moved to Anny's rest pose by the inverse of the fit's
   skinning, vertex by vertex: the model's target. A posed target's own joint deformation (a bent
   knee's folded skin) is otherwise carried into every driving pose (docs/results.md: the model's
   error on posed validation characters 79.7 -> 71.0 PMD).

*Props*: a separate part of the mesh (not its largest connected surface) that reaches beyond the fitted
body (farther than ``aniformer.trust.UNCOVERED_DISTANCE`` of its height: a sword, a staff, long hair, a
hat's brim), all such parts together at most ``PROP_SHARE`` of the surface, rides one template point,
the one nearest the part, as a rigid whole: vertex by vertex it would be carried by whichever limb is
nearest (a sword's tip by a leg) and torn. The template is read from the other faces only.
"""

from __future__ import annotations

import numpy as np
import roma
import torch

from aniformer.geometry import frames_per_chunk
from aniformer.registration import PROP_SHARE, BodyFit, anny_template, cached_fit
from aniformer.surface import SurfacePoints, closest_points, surface_parts
from aniformer.transfer import vertex_rotations

FIT_TRIES = 3  # fits of a character, each with its own sampling seed, until the self-check trusts one
FIT_AGREEMENT = 0.03  # of the body's height: two good fits of a driver read its clip this alike (bench/driver_consensus.py)


class Correspondence:
    """A mesh registered to an Anny topology: read its frames on the template, carry poses back.

    ``template_faces`` is the Anny topology's; ``fitted`` Anny's fitted body (``BodyFit``: given, or
    fitted here with ``fit_options``, or loaded if fitted before: ``fit_cached``, see
    ``aniformer.registration.cached_fit``); ``template`` its vertices snapped onto the mesh's surface;
    ``unposed_template`` those in Anny's rest pose; ``rms`` the root-mean-square distance of the fitted
    template's vertices to the mesh's surface and of the mesh's vertices to the template's (mesh units).
    ``aniformer.trust`` says whether to trust it."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, topology: str, fitted: BodyFit | None = None,
                 **fit_options):
        self.fit_seed = fit_options.get("seed", 0)
        self.vertices = np.asarray(vertices, np.float32)
        self.faces = np.asarray(faces, np.int64)
        self.topology = topology
        self.template_faces = anny_template(topology).faces
        self.fitted, self.fit_cached = ((fitted, False) if fitted is not None
                                        else cached_fit(self.vertices, self.faces, topology, **fit_options))
        self.parts, self.part_shares = surface_parts(self.vertices, self.faces)  # (N,) and per part; 0 the largest
        self.props = np.zeros(len(self.vertices), bool)  # (N,) vertices of props, each part carried rigidly
        self._embed()
        props = self._props()
        if props.any():
            self.props = props
            self._embed()
        self.rms = float(np.sqrt(np.square(np.concatenate([self.template_gap, self.mesh_gap[~self.props]])).mean()))
        self.unposed_template = self.fitted.unposed(self.template).astype(np.float32)

    def _embed(self) -> None:
        """The template on the mesh's faces other than props', and the mesh on the template: a prop's every
        vertex on the template point nearest the prop."""
        body_faces = np.flatnonzero(~self.props[self.faces[:, 0]])
        on_mesh = closest_points(self.fitted.vertices, self.vertices, self.faces[body_faces])
        self.template_on_mesh = SurfacePoints(body_faces[on_mesh.face], on_mesh.weights)
        self.template = self.to_template(self.vertices)
        self.mesh_on_template = closest_points(self.vertices, self.template, self.template_faces)
        self.template_gap = np.linalg.norm(self.fitted.vertices - self.template, axis=1)  # (V_a,) template to mesh
        self.mesh_gap = self._mesh_gap()  # (N,) mesh to template (a prop's: to its point)
        for part in np.unique(self.parts[self.props]):
            members = np.flatnonzero(self.parts == part)
            contact = members[self.mesh_gap[members].argmin()]
            self.mesh_on_template.face[members] = self.mesh_on_template.face[contact]
            self.mesh_on_template.weights[members] = self.mesh_on_template.weights[contact]
        if self.props.any():
            self.mesh_gap = self._mesh_gap()

    def _mesh_gap(self) -> np.ndarray:
        return np.linalg.norm(self.vertices - self.mesh_on_template.on(self.template, self.template_faces), axis=1)

    def _props(self) -> np.ndarray:
        """``(N,)``: the vertices of separate parts that reach beyond the fitted body, if all such parts together
        are at most ``PROP_SHARE`` of the surface (else none: a skirt or a coat is no prop)."""
        from aniformer.trust import UNCOVERED_DISTANCE

        beyond = np.bincount(self.parts, self.mesh_gap > UNCOVERED_DISTANCE * self.fitted.height,
                             minlength=len(self.part_shares)) > 0
        beyond[0] = False  # the body itself
        if self.part_shares[beyond].sum() > PROP_SHARE:
            return np.zeros(len(self.parts), bool)
        return beyond[self.parts]

    def record(self) -> dict:
        """The registration as animation.json's ``registered`` records it: surface distance, template size,
        whether the fit was kept from an earlier run, its sampling seed (``register_mesh``'s try) and props."""
        return {"rms_m": round(self.rms, 5), "template_vertices": len(self.template), "fit_cached": self.fit_cached,
                "fit_seed": self.fit_seed, "props": self.prop_record()}

    def prop_record(self) -> dict:
        """The props as animation.json records them: how many separate parts, their share of the surface."""
        parts = np.unique(self.parts[self.props])
        return {"parts": len(parts), "surface_share": round(float(self.part_shares[parts].sum()), 4)}

    def to_template(self, frames: np.ndarray) -> np.ndarray:
        """Frames ``(..., N, 3)`` of the mesh's topology as ``(..., V_a, 3)`` on Anny's."""
        return self.template_on_mesh.on(frames, self.faces)

    def from_template(self, posed: np.ndarray) -> np.ndarray:
        """The mesh in the poses of ``posed (T, V_a, 3)`` (the template moved) -> ``(T, N, 3)`` float32: each
        vertex rides its template point, its offset from it turned by the template's local rotation there,
        the weighted rotation mean of its face's corners (a few frames at a time: `frames_per_chunk`)."""
        chunk = frames_per_chunk(len(self.vertices))
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
    # components, then rotations first: sums over them add whole arrays, where sums over a last axis of 3 or 4
    # entries are slow small reductions in torch (the carry-back at 18k vertices: 2.9 -> 1.9 s, docs/benchmarks.md)
    q = quaternions.movedim(-1, 0).movedim(-1, 1).contiguous()  # (4, K, ...)
    weights = weights.expand(quaternions.shape[:-1]).movedim(-1, 0)  # (K, ...)

    def dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3]

    def unit(a: torch.Tensor) -> torch.Tensor:
        return a / dot(a, a).sqrt().clamp_min(1e-12)  # as torch.nn.functional.normalize

    aligned = torch.where(dot(q, q[:, :1]) < 0, -q, q)
    weighted = weights * aligned
    mean = unit(weighted.sum(1))
    for _ in range(max_iterations):
        previous, mean = mean, unit((weighted * dot(aligned, mean[:, None])).sum(1))
        if (mean - previous).abs().max() < tolerance:
            break
    return mean.movedim(0, -1)


def _badness(checks) -> float:
    """The worst of ``checks`` as a share of its limit: at most 1 where the self-check trusts them all."""
    return max(c.value / c.limit for c in checks)


def register_mesh(vertices: np.ndarray, faces: np.ndarray, topology: str, tries: int = FIT_TRIES,
                  **fit_options) -> Correspondence:
    """A character's mesh registered onto ``topology`` (``fit_options``: ``fit_template``'s): fitted with
    sampling seed 0, 1, ... while the self-check's registration checks (``aniformer.trust.registration_checks``)
    refuse the fit, at most ``tries`` times; the fit they trust most is kept (its ``fit_seed`` says which try)."""
    from aniformer.trust import registration_checks

    best = None
    for seed in range(tries):
        fit = Correspondence(vertices, faces, topology, **fit_options, seed=seed)
        badness = _badness(registration_checks(fit))
        if best is None or badness < best[0]:
            best = (badness, fit)
        if badness <= 1.0:
            break
    return best[1]


def part_rms_distance(first: np.ndarray, second: np.ndarray, topology: str) -> float:
    """The worst body part's RMS distance between two sequences ``(T, V_a, 3)`` on ``topology``'s template: how far
    apart two fits of one clip read it (two good fits put each template vertex on the same body point)."""
    from aniformer.trust import part_labels

    parts, _ = part_labels(topology)
    distance = np.square(first - second).sum(-1)
    return float(max(np.sqrt(distance[:, parts == k].mean()) for k in np.unique(parts)))


def register_clip(frames: np.ndarray, faces: np.ndarray, topology: str, candidates: int = 3):
    """A driving clip of a foreign topology registered on the whole clip, not its first frame alone:
    (the ``Correspondence``, its ``aniformer.trust.Trust``).

    Fits on up to ``candidates`` frames spread over the clip (first frame first), each checked by the self-check
    (its own fit, and the stretch of the template read from frames over the whole clip), until two fits it trusts
    read the clip alike (``part_rms_distance`` within ``FIT_AGREEMENT`` of the height); keeps the one it trusts most. Stopping at
    the first trusted fit kept wrong ones that a later frame's fit would have shown (docs/results.md)."""
    from aniformer.trust import Trust, registration_checks, stretch_check

    shown = frames[np.unique(np.linspace(0, len(frames) - 1, min(len(frames), 64)).round().astype(int))]
    fits = []  # (badness, fit, trust, the clip read on the template)
    for k in np.unique(np.linspace(0, len(frames) - 1, candidates).round().astype(int)):
        fit = Correspondence(frames[k], faces, topology)
        read = fit.to_template(shown)
        trust = Trust((*registration_checks(fit, "driver"),
                       stretch_check(read, fit.template, fit.template_faces, "driver on the template")))
        agreed = trust.ok and any(
            other.ok and part_rms_distance(read, other_read, topology) <= FIT_AGREEMENT * fit.fitted.height
            for _, _, other, other_read in fits)
        fits.append((_badness(trust.checks), fit, trust, read))
        if agreed:
            break
    _, fit, trust, _ = min(fits, key=lambda entry: entry[0])
    return fit, trust
