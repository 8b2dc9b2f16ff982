"""Whether to trust a registration and the animation made through it: never ship a shredded mesh.

A small surface distance does not mean a right correspondence: a body fitted facing backwards, or
with an arm lying along the torso, can be within 2 cm of the mesh on average. Three views that a
wrong correspondence cannot all pass (measured in docs/results.md#the-self-check):

- ``part gap``: per body part (head, torso, upper arms, forearms, hands, thighs, shins, feet),
  the RMS distance of the fitted Anny body's vertices to the mesh, over the body's height: a limb
  fitted where the mesh has none, or a foot pointing backwards, is far from the surface;
- ``uncovered``: the share of the mesh's surface farther from the template than
  ``UNCOVERED_DISTANCE`` of the height (a mesh limb no template limb lies on: it would be carried
  by the wrong part), props aside (``aniformer.correspondence``: carried rigidly);
- ``flipped``: the share of the fitted body's vertices whose normal points against the mesh's
  surface there (a template turned inside out, or a limb through the torso);
- ``part flipped``: the same share per body part, the worst part's (a hand turned over is too small
  a share of the body for ``flipped``);
- ``stretch`` (of a result): the share of the mesh's edge length, in the worst frame, stretched or
  squashed beyond a factor ``STRETCH_FACTOR`` against the same mesh at rest (vertices carried across
  body parts); for a registered driver the same on the template read from every frame;
- ``near limits``: per registered mesh, its part gap, its flipped share and the result's stretch,
  each as a share of its limit, summed: each view alone is noisy, and a wrong fit was seen just
  under all three limits at once.

Each check's limit sits between the good and the deliberately broken cases (``injected_failures``)
of the calibration on validation pairs (``bench/trust_calibration.py``).
"""

from __future__ import annotations

import functools
from dataclasses import asdict, dataclass

import numpy as np

from aniformer.geometry import frames_per_chunk
from aniformer.transfer import mesh_edges

PART_OF_BONE = (  # bone-name prefix -> body part; sides come from the bone's .L / .R
    ("neck", "head"), ("head", "head"), ("eye", "head"), ("upperarm", "upper arm"), ("shoulder", "upper arm"),
    ("lowerarm", "forearm"), ("wrist", "hand"), ("finger", "hand"), ("metacarpal", "hand"),
    ("upperleg", "thigh"), ("lowerleg", "shin"), ("foot", "foot"), ("toe", "foot"),
)
UNCOVERED_DISTANCE = 0.06  # of the body's height (~10 cm): beyond it, a mesh point has no template part
STRETCH_FACTOR = 3.0  # a tear; the deepest natural joint bends reach 1 % of the edge length beyond it (369 v)
LIMITS = {"part gap": 0.025, "uncovered": 0.02, "flipped": 0.08, "part flipped": 0.4, "stretch": 0.02,
          "near limits": 2.2}
HINTS = {
    "part gap": "a body part of the fit is off the mesh",
    "uncovered": "part of the mesh has no body part of the fit on it",
    "flipped": "the fit's surface turns against the mesh's",
    "part flipped": "a body part of the fit turns against the mesh (a hand or foot turned over)",
    "stretch": "the result tears the mesh (vertices carried across body parts)",
    "near limits": "part gap, flipped and stretch are all close to their limits (summed as shares of them)",
}


@dataclass(frozen=True)
class Check:
    """One trust check: its value, the limit it must not pass, and where it was worst."""

    name: str
    value: float
    limit: float
    where: str = ""

    @property
    def ok(self) -> bool:
        return bool(self.value <= self.limit)

    def describe(self) -> str:
        where = f" ({self.where})" if self.where else ""
        return f"{self.name} {self.value:.3f} > {self.limit:.3f}{where}: {HINTS[self.name]}"


@functools.cache
def part_labels(topology: str) -> tuple[np.ndarray, tuple[str, ...]]:
    """(part index per template vertex, part names) of an Anny topology, from each vertex's
    strongest bone."""
    from aniformer.synth.bodies import BodyModel

    body = BodyModel(topology)
    model = body._model
    weights, bones = model.vertex_bone_weights.numpy(), model.vertex_bone_indices.numpy()
    strongest = bones[np.arange(len(bones)), weights.argmax(1)]
    names = []
    for label in body.bone_labels:
        part = next((p for prefix, p in PART_OF_BONE if label.startswith(prefix)), "torso")
        side = label.rsplit(".", 1)[1] if label.endswith((".L", ".R")) and part not in ("torso", "head") else ""
        names.append(f"{part} {side}".strip())
    parts = tuple(dict.fromkeys(names))
    return np.array([parts.index(names[b]) for b in strongest]), parts


def registration_checks(correspondence, role: str = "") -> list[Check]:
    """``part gap``, ``uncovered``, ``flipped`` and ``part flipped`` of an
    ``aniformer.correspondence.Correspondence`` (of the mesh of ``role``: target, driver)."""
    height = correspondence.fitted.height
    parts, names = part_labels(correspondence.topology)
    gaps = np.array([np.sqrt(np.square(correspondence.template_gap[parts == k]).mean()) if (parts == k).any() else 0.0
                     for k in range(len(names))]) / height
    worst = int(gaps.argmax())
    faces, vertices = correspondence.faces, correspondence.vertices
    area = np.linalg.norm(np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]],
                                   vertices[faces[:, 2]] - vertices[faces[:, 0]]), axis=1)
    far = (correspondence.mesh_gap[faces].mean(1) > UNCOVERED_DISTANCE * height) & ~correspondence.props[faces[:, 0]]
    uncovered = float(area[far].sum() / max(area.sum(), 1e-12))
    from aniformer.surface import normals

    template_normals, _ = normals(correspondence.fitted.vertices, correspondence.template_faces)
    _, mesh_normals = normals(vertices, faces)
    mesh_normals = mesh_normals[correspondence.template_on_mesh.face]
    against = (template_normals * mesh_normals).sum(1) < 0
    part_flipped = np.array([against[parts == k].mean() if (parts == k).any() else 0.0 for k in range(len(names))])
    turned = int(part_flipped.argmax())
    return [Check("part gap", float(gaps[worst]), LIMITS["part gap"], f"{role} {names[worst]}".strip()),
            Check("uncovered", uncovered, LIMITS["uncovered"], role),
            Check("flipped", float(against.mean()), LIMITS["flipped"], role),
            Check("part flipped", float(part_flipped[turned]), LIMITS["part flipped"], f"{role} {names[turned]}".strip())]


def stretch_check(frames: np.ndarray, rest: np.ndarray, faces: np.ndarray, what: str = "result",
                  chunk: int | None = None) -> Check:
    """``stretch`` of ``frames (T, N, 3)`` against ``rest (N, 3)`` of one mesh: the worst frame's share of
    edge length beyond ``STRETCH_FACTOR`` either way (``chunk`` frames at a time, default `frames_per_chunk`)."""
    import torch

    chunk = chunk or frames_per_chunk(rest.shape[0])
    i, j = (torch.from_numpy(e) for e in mesh_edges(np.asarray(faces, np.int64), rest.shape[0]))
    rest_length = np.linalg.norm(rest[i] - rest[j], axis=1) + 1e-9
    # squared lengths against squared bounds, in torch: 0.65 -> 0.2 s for 300 frames of 18k vertices
    longest = torch.from_numpy((STRETCH_FACTOR * rest_length) ** 2).float()
    shortest = torch.from_numpy((rest_length / STRETCH_FACTOR) ** 2).float()
    share_of_length = torch.from_numpy(rest_length / rest_length.sum()).double()
    shares = []
    for lo in range(0, len(frames), chunk):
        batch = torch.from_numpy(np.ascontiguousarray(frames[lo : lo + chunk], np.float32))
        edge = (batch.index_select(1, i) - batch.index_select(1, j)).square()
        squared = edge[..., 0] + edge[..., 1] + edge[..., 2]  # a sum over the last axis of 3 is slow in torch
        shares.append(((squared > longest) | (squared < shortest)).double() @ share_of_length)
    shares = torch.cat(shares)
    worst = int(shares.argmax())
    return Check("stretch", float(shares[worst]), LIMITS["stretch"], f"{what}, frame {worst}")


@dataclass(frozen=True)
class Trust:
    """The checks of one animation; ``ok`` when every check is within its limit."""

    checks: tuple[Check, ...]

    @property
    def ok(self) -> bool:
        return all(c.ok for c in self.checks)

    def reason(self) -> str:
        return "; ".join(c.describe() for c in self.checks if not c.ok)

    def to_dict(self) -> dict:
        return {"ok": self.ok, "checks": [{**asdict(c), "ok": c.ok} for c in self.checks]}


def animation_trust(result: np.ndarray, target: np.ndarray, target_faces: np.ndarray, target_fit=None,
                    driver_trust: Trust | None = None) -> Trust:
    """The self-check of an animation ``result (T, N, 3)`` of ``target (N, 3)``: the driver's registration
    (``driver_trust``, from ``aniformer.correspondence.register_clip``), the target's (``target_fit``, a
    ``Correspondence``), each where there was one, the result's stretch, and ``near limits``."""
    registered = [list(driver_trust.checks)] if driver_trust is not None else []
    if target_fit is not None:
        registered.append(registration_checks(target_fit, "target"))
    stretch = stretch_check(result, target, target_faces)
    near = [Check("near limits", stretch.value / stretch.limit + sum(c.value / c.limit for c in checks
                                                                      if c.name in ("part gap", "flipped")),
                  LIMITS["near limits"], checks[0].where.split(" ")[0]) for checks in registered]
    return Trust((*(c for checks in registered for c in checks), stretch, *near))


def injected_failures(correspondence) -> dict[str, object]:
    """Deliberately broken fits of a good registration, to calibrate and test the checks, as
    ``aniformer.registration.BodyFit`` by name: ``heading`` (turned 180 degrees about its own
    feet-to-head axis: facing backwards), ``tilt`` (turned 90 degrees about a horizontal axis: a y-up
    file read as z-up), ``swapped arm`` (the left arm's vertices on their mirror partners of the right arm)."""
    import roma
    import scipy.spatial
    import torch

    from aniformer.registration import BodyFit, body_axis
    from aniformer.synth.bodies import BodyModel

    fitted = correspondence.fitted
    centre = fitted.vertices.mean(0)

    def turned(axis: np.ndarray, angle: float) -> BodyFit:
        rotation = roma.rotvec_to_rotmat(torch.from_numpy(axis / np.linalg.norm(axis) * angle)).numpy()
        shift = np.broadcast_to(centre - rotation.T @ centre, fitted.vertices.shape)
        to_rest = np.concatenate([fitted.to_rest[..., :3] @ rotation.T,  # a point is turned back, then unposed
                                  fitted.unposed(shift)[..., None]], -1)
        return BodyFit(((fitted.vertices - centre) @ rotation.T + centre).astype(np.float32), fitted.height, fitted.loss,
                       to_rest)

    up = body_axis(fitted.vertices, correspondence.template_faces).astype(np.float64)
    across = np.cross(up, [0.0, 0.0, 1.0] if abs(up[2]) < 0.9 else [1.0, 0.0, 0.0])
    body = BodyModel(correspondence.topology)
    rest = body.pose(np.full((1, 6), 0.5, np.float32), np.zeros((1, len(body.bone_labels), 3), np.float32))[0]
    _, mirror = scipy.spatial.cKDTree(rest * [-1, 1, 1]).query(rest)  # Anny is symmetric in x at rest
    parts, names = part_labels(correspondence.topology)
    left_arm = np.isin(parts, [names.index(n) for n in ("upper arm L", "forearm L", "hand L")])
    swapped, swapped_to_rest = fitted.vertices.copy(), fitted.to_rest.copy()
    swapped[left_arm], swapped_to_rest[left_arm] = swapped[mirror[left_arm]], swapped_to_rest[mirror[left_arm]]
    return {"heading": turned(up, np.pi), "tilt": turned(across, np.pi / 2),
            "swapped arm": BodyFit(swapped, fitted.height, fitted.loss, swapped_to_rest)}
