"""Anny body model wrapper: sample adult identities and pose them in batches.

AniFormer needs many identities performing the same motions. SMPL/DFAUST are not freely
redistributable, so identities come from the open Anny model (``pip install anny``): a
phenotype vector (gender, age, muscle, weight, height, proportions, all in [0, 1]) picks the
body shape and per-bone rotations pose it. Everything here is float32 on CPU with plain
linear blend skinning, so the same inputs give bit-identical vertices.

Building an Anny model the first time on a machine is slow (tens of seconds to minutes, a few
hundred MB written to ``~/.cache/anny`` or ``$ANNY_CACHE_DIR``); later builds load that cache
in well under a second. ``BodyModel`` keeps one built model per topology per process.
"""

from __future__ import annotations

import functools
import types

import anny
import numpy as np
import roma
import torch
from anny.shape_distribution import SimpleShapeDistribution

#: Supported Anny topologies and their vertex counts.
TOPOLOGIES: dict[str, int] = {
    "notoes_collapse3pc": 369,
    "notoes_collapse5pc": 615,
    "notoes_collapse10pc": 1229,
    "notoes": 12272,
}

#: Anny's default phenotype parameters, in the column order of an identity vector.
PHENOTYPE_KEYS: tuple[str, ...] = ("gender", "age", "muscle", "weight", "height", "proportions")

ADULT_AGE_YEARS = (18.0, 70.0)


def sample_identities(n: int, seed: int) -> np.ndarray:
    """``n`` adult phenotype vectors, (n, len(PHENOTYPE_KEYS)) float32, a function of ``seed``.

    Anny's ``SimpleShapeDistribution`` (height, weight, muscle and proportions conditioned on
    age and gender, calibrated on WHO data) with a morphological age uniform in 18-70 years.
    """
    # The distribution only reads dtype, device and phenotype labels from the model, so a
    # stand-in avoids building a body model just to sample phenotypes.
    spec = types.SimpleNamespace(dtype=torch.float64, device=torch.device("cpu"), phenotype_labels=list(PHENOTYPE_KEYS))
    low, high = (torch.tensor(v, dtype=torch.float64) for v in ADULT_AGE_YEARS)
    distribution = SimpleShapeDistribution(spec, morphological_age_distribution=torch.distributions.Uniform(low, high))
    with torch.random.fork_rng(devices=[]):  # the distribution draws from torch's global RNG
        torch.manual_seed(seed)
        _, phenotypes = distribution.sample(n)
    columns = [phenotypes[key].clamp(0.0, 1.0) for key in PHENOTYPE_KEYS]
    return torch.stack(columns, dim=1).numpy().astype(np.float32)


@functools.cache
def _anny_model(topology: str) -> anny.Anny:
    """One built Anny model per topology per process (the cold build is the expensive part)."""
    model = anny.Anny(topology=topology, skinning_method="lbs").to(torch.float32)
    model.eval()
    return model


class BodyModel:
    """An Anny topology that turns (identity, per-bone rotations, translation) into vertices.

    Pose convention (Anny's ``local-ref``): ``rotvecs[:, b]`` rotates bone ``b`` relative to its
    parent, expressed in world-aligned axes of the rest pose, so a bone's world rotation is the
    product of the rotations along its chain from the root. Zeros give Anny's rest (A-)pose.
    Coordinates are metres, z up, the body facing -y, the root at the origin.
    """

    def __init__(self, topology: str = "notoes_collapse10pc"):
        if topology not in TOPOLOGIES:
            raise ValueError(f"unknown topology {topology!r}; valid: {sorted(TOPOLOGIES)}")
        self.topology = topology
        self._model = _anny_model(topology)
        self.faces: np.ndarray = self._model.get_triangular_faces().numpy().astype(np.int64)
        self.num_vertices: int = int(self._model.template_vertices.shape[0])
        self.bone_labels: list[str] = list(self._model.bone_labels)
        self.bone_parents: list[int] = [int(p) for p in self._model.bone_parents]
        # pose() passes identities to Anny as a tensor, whose columns follow the model's labels.
        assert tuple(self._model.phenotype_labels) == PHENOTYPE_KEYS

    def pose(
        self,
        identities: np.ndarray,
        rotvecs: np.ndarray,
        translation: np.ndarray | None = None,
    ) -> np.ndarray:
        """Vertices (N, V, 3) float32 for identities (N, K), rotvecs (N, bones, 3), translation (N, 3)."""
        identities = torch.as_tensor(np.asarray(identities, dtype=np.float32))
        rotvecs = torch.as_tensor(np.asarray(rotvecs, dtype=np.float32))
        n = identities.shape[0]
        if identities.shape != (n, len(PHENOTYPE_KEYS)):
            raise ValueError(f"identities must be (N, {len(PHENOTYPE_KEYS)}), got {tuple(identities.shape)}")
        if rotvecs.shape != (n, len(self.bone_labels), 3):
            raise ValueError(f"rotvecs must be ({n}, {len(self.bone_labels)}, 3), got {tuple(rotvecs.shape)}")
        deltas = torch.eye(4).repeat(n, len(self.bone_labels), 1, 1)
        deltas[..., :3, :3] = roma.rotvec_to_rotmat(rotvecs)
        # The rest shape (blendshapes, bone frames) depends on the identity only: compute it
        # once per distinct identity (clips repeat one identity over all their frames).
        unique, index = torch.unique(identities, dim=0, return_inverse=True)
        with torch.no_grad():  # not inference_mode: roma caches tensors made here, and autograd refuses them
            rest = self._model(phenotype_kwargs=unique)  # also poses them at rest: cheap
            transforms, _ = self._model.get_bone_transforms(deltas, rest["rest_bone_poses"][index])
            vertices = self._model.get_skinned_vertices(rest["rest_vertices"][index], transforms)
        vertices = vertices.numpy()
        if translation is not None:
            vertices = vertices + np.asarray(translation, dtype=np.float32)[:, None, :]
        return vertices.astype(np.float32, copy=False)
