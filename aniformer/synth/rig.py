"""The Anny rig's controlled bones and world-space posing, shared by the action library
(``motions``) and the pose-space families (``poses``).

Posing works in world space, which is what makes the limbs land where intended: every
controlled bone gets an absolute world rotation A (relative to Anny's reference A-pose),
built from anatomical angles (flexion, abduction, internal rotation, elbow/knee bend), and
its local rotation for ``BodyModel.pose`` is D = Aₚᵀ A with Aₚ the world rotation of the
nearest controlled ancestor (Anny's ``local-ref`` convention: a bone's world rotation is the
product of the local ones along its chain). Uncontrolled bones (twist bones, fingers, toes)
keep D = I and follow their parent.

Axes: metres, z up, the body faces -y, its left is +x. Angles are radians and are written for
the left side; the right side uses the mirror image (x -> -x).
"""

from __future__ import annotations

import numpy as np
import roma
import torch

# Each controlled bone and its nearest controlled ancestor in the Anny rig (checked in tests).
CONTROLLED_PARENTS: dict[str, str | None] = {
    "root": None,
    "spine04": "root",
    "spine02": "spine04",
    "head": "spine02",
    **{
        f"{bone}.{side}": parent
        for side in "LR"
        for bone, parent in (
            ("clavicle", "spine02"),
            ("upperarm01", f"clavicle.{side}"),
            ("lowerarm01", f"upperarm01.{side}"),
            ("upperleg01", "root"),
            ("lowerleg01", f"upperleg01.{side}"),
            ("foot", f"lowerleg01.{side}"),
        )
    },
}

# Left-limb directions in Anny's reference pose (mean over adults; individual bodies are
# within ~4 degrees). The reference arm hangs 50 degrees from vertical with the elbow bent 42.
_UPPER_ARM_REF = (0.650, -0.027, -0.759)
_FOREARM_REF = (0.516, -0.684, -0.515)
_THIGH_REF = (0.084, -0.061, -0.995)
_SHIN_REF = (0.100, 0.075, -0.992)
# Nominal adult hip joint and ankle (left side, metres) for keeping planted feet in place.
_HIP = (0.112, 0.009, -0.011)
_ANKLE = (0.186, 0.018, -0.807)
_THIGH_LENGTH, _SHIN_LENGTH = 0.372, 0.430

_X, _Y, _Z = torch.eye(3, dtype=torch.float64)
_MIRROR = torch.diag(torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64))


def _vec(values) -> torch.Tensor:
    return torch.tensor(values, dtype=torch.float64)


def _rot(axis: torch.Tensor, angle) -> torch.Tensor:
    """Rotations (T, 3, 3) about a fixed axis by angles (T,) (or a scalar)."""
    angle = torch.as_tensor(angle, dtype=torch.float64).reshape(-1, 1)
    return roma.rotvec_to_rotmat(angle * (axis / axis.norm()))


def _fraction(rotation: torch.Tensor, weight: float) -> torch.Tensor:
    """The rotation scaled along its geodesic from identity (weight 0.5: half-way)."""
    return roma.rotvec_to_rotmat(weight * roma.rotmat_to_rotvec(rotation))


def _frame(direction: torch.Tensor, bend: torch.Tensor) -> torch.Tensor:
    """Orthonormal frame (direction, bend orthogonalised, their cross product) as columns."""
    return roma.special_gramschmidt(torch.stack([direction, bend], dim=-1))


def _hinge_limb(proximal, distal, bend_to):
    """For a two-segment reference limb: the world rotation making it hang straight down with
    its hinge bending towards ``bend_to``, the hinge axis (reference pose) and the reference
    bend angle."""
    proximal, distal = _vec(proximal), _vec(distal)
    proximal, distal = proximal / proximal.norm(), distal / distal.norm()
    bend = distal - (distal @ proximal) * proximal
    angle = float(torch.atan2(bend.norm(), distal @ proximal))
    base = _frame(-_Z, bend_to) @ _frame(proximal, bend).T
    hinge = torch.linalg.cross(proximal, bend / bend.norm())
    return base, hinge, angle


_ARM_BASE, _ELBOW_AXIS, _ELBOW_REF = _hinge_limb(_UPPER_ARM_REF, _FOREARM_REF, -_Y)
_LEG_BASE, _KNEE_AXIS, _KNEE_REF = _hinge_limb(_THIGH_REF, _SHIN_REF, _Y)
_EYE = torch.eye(3, dtype=torch.float64)


class _Clip:
    """Builds one motion: world rotations of controlled bones and the root offset over time."""

    def __init__(self, seed: int, frames: int):
        self.rng = np.random.default_rng(seed)
        self.frames = frames
        self.s = torch.arange(frames, dtype=torch.float64) / frames  # clip time in [0, 1)
        self.world: dict[str, torch.Tensor] = {}
        self.translation = torch.zeros(frames, 3, dtype=torch.float64)
        self.amp = self.uniform(0.8, 1.1)
        # Left/right asymmetry: amplitude factors and a phase lag (in cycles) of the right side.
        self.side_amp = {"L": 1.0 + self.uniform(-0.12, 0.12), "R": 1.0 + self.uniform(-0.12, 0.12)}
        self.side_lag = {"L": 0.0, "R": self.uniform(-0.03, 0.03)}

    def uniform(self, low: float, high: float) -> float:
        return float(self.rng.uniform(low, high))

    def wave(self, cycles: float, phase: float, side: str = "L") -> torch.Tensor:
        """sin of the motion phase, in [-1, 1]."""
        return torch.sin(2 * torch.pi * (cycles * self.s + phase + self.side_lag[side]))

    def pulse(self, cycles: float, phase: float, side: str = "L") -> torch.Tensor:
        """Smooth 0 -> 1 -> 0 once per cycle."""
        return 0.5 - 0.5 * torch.cos(2 * torch.pi * (cycles * self.s + phase + self.side_lag[side]))

    def _set(self, bone: str, side: str, rotation: torch.Tensor) -> None:
        rotation = rotation.expand(self.frames, 3, 3)
        self.world[f"{bone}.{side}"] = rotation if side == "L" else _MIRROR @ rotation @ _MIRROR

    @staticmethod
    def _swing(flex, abduct, internal=0.0) -> torch.Tensor:
        """Limb rotation from hanging straight down: internal rotation about the limb's axis,
        abduction away from the midline, then flexion forward."""
        return _rot(-_X, flex) @ _rot(-_Y, abduct) @ _rot(-_Z, internal)

    def arm(self, side: str, flex=0.0, abduct=0.2, internal=0.0, elbow=0.25) -> None:
        """Upper arm and forearm; elbow is the bend from straight, the forearm going forward
        (and up, once the arm is raised)."""
        upper = self._swing(flex, abduct, internal) @ _ARM_BASE
        self._set("upperarm01", side, upper)
        self._set("lowerarm01", side, upper @ _rot(_ELBOW_AXIS, torch.as_tensor(elbow) - _ELBOW_REF))

    def leg(self, side: str, flex=0.0, abduct=0.05, knee=0.1, toes=0.0, internal=0.0) -> None:
        """Thigh, shin and foot; knee bends the shin backwards, toes > 0 points the foot down
        (the foot stays level with the ground otherwise)."""
        thigh = self._swing(flex, abduct, internal) @ _LEG_BASE
        self._set("upperleg01", side, thigh)
        self._set("lowerleg01", side, thigh @ _rot(_KNEE_AXIS, torch.as_tensor(knee) - _KNEE_REF))
        self._set("foot", side, _rot(_X, toes))

    def planted_leg(self, side: str, toes=0.0) -> None:
        """Leg reaching the nominal standing ankle position whatever the root does: two-bone
        IK on nominal adult lengths (other bodies' feet land within millimetres of it)."""
        root = self.world.get("root", _EYE.expand(self.frames, 3, 3))
        mirror = _vec([1.0 if side == "L" else -1.0, 1.0, 1.0])
        hip = root @ (mirror * _vec(_HIP)) + self.translation
        target = mirror * (mirror * _vec(_ANKLE) - hip)  # hip to ankle, in left-side axes
        reach = target.norm(dim=-1).clamp(max=0.999 * (_THIGH_LENGTH + _SHIN_LENGTH))
        hip_angle = torch.acos((_THIGH_LENGTH**2 + reach**2 - _SHIN_LENGTH**2) / (2 * _THIGH_LENGTH * reach))
        knee = torch.pi - torch.acos((_THIGH_LENGTH**2 + _SHIN_LENGTH**2 - reach**2) / (2 * _THIGH_LENGTH * _SHIN_LENGTH))
        to_ankle = _frame(target, _Y.expand_as(target))  # columns: to the ankle, backwards, ...
        thigh_dir = (
            torch.cos(hip_angle)[:, None] * to_ankle[..., 0] - torch.sin(hip_angle)[:, None] * to_ankle[..., 1]
        )  # tilted forward: the knee points forward
        thigh = _frame(thigh_dir, _Y.expand_as(thigh_dir)) @ _frame(-_Z, _Y).T @ _LEG_BASE
        self._set("upperleg01", side, thigh)
        self._set("lowerleg01", side, thigh @ _rot(_KNEE_AXIS, knee - _KNEE_REF))
        self._set("foot", side, _rot(_X, toes))

    def torso(self, chest: torch.Tensor, head_follow: float = 0.5) -> None:
        """Chest world rotation, spread over the spine, the head following part of it."""
        pelvis = self.world.get("root", _EYE.expand(self.frames, 3, 3))
        chest = chest.expand(self.frames, 3, 3)
        self.world["spine04"] = pelvis @ _fraction(pelvis.transpose(-1, -2) @ chest, 0.5)
        self.world["spine02"] = chest
        self.world["head"] = _fraction(chest, head_follow)

    def clavicle(self, side: str, raise_=0.0, forward=0.0) -> None:
        """Shoulder shrug (raise_) and protraction (forward), on top of the chest rotation."""
        chest = self.world.get("spine02", _EYE.expand(self.frames, 3, 3))
        local = _rot(-_Y, raise_) @ _rot(-_Z, forward)
        self.world[f"clavicle.{side}"] = chest @ (local if side == "L" else _MIRROR @ local @ _MIRROR)

    def add_noise(self, scale: float = 0.03) -> None:
        """Smooth per-joint wobble: two random low-frequency sinusoids per axis and bone (a
        third of it on the root and legs, whose errors move the feet)."""
        s = self.s.numpy()[None, :, None]
        for bone in self.world:
            cycles = self.rng.uniform(0.5, 2.0, size=(2, 1, 3))
            phase = self.rng.uniform(0.0, 1.0, size=(2, 1, 3))
            amplitude = self.rng.normal(0.0, scale / 2, size=(2, 1, 3))
            if bone == "root" or "leg" in bone or "foot" in bone:
                amplitude /= 3
            rotvec = (amplitude * np.sin(2 * np.pi * (cycles * s + phase))).sum(0)
            self.world[bone] = roma.rotvec_to_rotmat(torch.from_numpy(rotvec)) @ self.world[bone]

    def crouch(self, side: str, knee, abduct=0.05, toes=0.0) -> torch.Tensor:
        """Bent standing leg with the foot under the hip (thigh forward by half the knee bend,
        shin back by the other half); returns how far the hip drops."""
        knee = torch.as_tensor(knee, dtype=torch.float64)
        self.leg(side, flex=knee / 2, abduct=abduct, knee=knee, toes=toes)
        return (_THIGH_LENGTH + _SHIN_LENGTH) * (1 - torch.cos(knee / 2))


def local_rotvecs(world: dict[str, torch.Tensor], bone_labels: list[str]) -> torch.Tensor:
    """``(N, bones, 3)`` local rotation vectors for ``BodyModel.pose`` from the world rotations
    ``(N, 3, 3)`` of every controlled bone (D = Aₚᵀ A, Aₚ the nearest controlled ancestor's)."""
    n = next(iter(world.values())).shape[0]
    rotvecs = torch.zeros(n, len(bone_labels), 3, dtype=torch.float64)
    for bone, parent in CONTROLLED_PARENTS.items():
        local = world[bone] if parent is None else world[parent].transpose(-1, -2) @ world[bone]
        rotvecs[:, bone_labels.index(bone)] = roma.rotmat_to_rotvec(local)
    return rotvecs
