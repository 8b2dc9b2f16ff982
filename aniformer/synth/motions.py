"""Procedural DFAUST-like motions for the Anny rig.

No motion capture ships with Anny, so each action class is a small program: periodic joint
angles with randomised amplitude, tempo (cycles per clip), phase, left/right asymmetry and
smooth per-joint noise, all drawn from ``np.random.default_rng(seed)``. A clip is ``frames``
evenly spaced samples of one continuous motion, like the paper's 30 frames per DFAUST clip.

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

from dataclasses import dataclass

import numpy as np
import roma
import torch

ACTIONS: tuple[str, ...] = (
    "jumping_jacks",
    "punching",
    "knee_raises",
    "shake_arms",
    "shake_hips",
    "shake_shoulders",
    "running_on_spot",
    "one_leg_jump",
    "one_leg_loose",
    "light_hopping_stiff",
    "light_hopping_loose",
    "chicken_wings",
    "hips",
    "jiggle_on_toes",
)

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


@dataclass(frozen=True)
class Motion:
    """One sampled clip: per-frame local bone rotations and root offset for ``BodyModel.pose``."""

    action: str
    seed: int
    rotvecs: np.ndarray  # (frames, bone_count, 3) float32
    translation: np.ndarray  # (frames, 3) float32, metres


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


def _relu2(x: torch.Tensor) -> torch.Tensor:
    """max(x, 0)^2: zero half the time, with a continuous slope."""
    return x.clamp(min=0) ** 2


def _jumping_jacks(c: _Clip) -> None:
    cycles, phase = c.uniform(0.9, 1.25), c.uniform(0, 1)
    airborne = c.pulse(2 * cycles, 2 * phase + 0.5)  # a hop at each opening and closing
    c.torso(_EYE)
    drops = []
    for side in "LR":
        spread = c.pulse(cycles, phase, side) * c.side_amp[side]
        c.arm(side, flex=0.15, abduct=0.25 + spread * (2.55 * c.amp - 0.25), elbow=0.3)
        c.clavicle(side, raise_=0.3 * spread)
        knee = 0.1 + 0.5 * (1 - airborne)
        drops.append(c.crouch(side, knee, abduct=0.05 + 0.2 * spread * c.amp, toes=0.35 * airborne))
    c.translation[:, 2] = 0.07 * c.amp * airborne - torch.maximum(*drops)


def _punching(c: _Clip) -> None:
    cycles, phase = c.uniform(1.5, 2.5), c.uniform(0, 1)
    reach = {side: c.pulse(cycles, phase + 0.5 * (side == "R"), side) ** 1.5 for side in "LR"}
    c.torso(_rot(_Z, -0.2 * c.amp * (reach["L"] - reach["R"])))
    drops = []
    for side in "LR":
        w = reach[side] * c.side_amp[side]
        c.arm(
            side,
            flex=0.35 + w * (1.45 * c.amp - 0.35),
            abduct=0.15 - 0.3 * w,
            internal=0.35 - 0.25 * w,
            elbow=2.2 - 2.1 * w,
        )
        c.clavicle(side, forward=0.25 * w)
        drops.append(c.crouch(side, 0.3, abduct=0.1))
    c.translation[:, 2] = -drops[0]


def _knee_raises(c: _Clip) -> None:
    cycles, phase = c.uniform(1.0, 1.5), c.uniform(0, 1)
    c.torso(_EYE)
    for side, sign in (("L", 1.0), ("R", -1.0)):
        lift = _relu2(sign * c.wave(cycles, phase, side)) * c.side_amp[side] * c.amp
        other = _relu2(-sign * c.wave(cycles, phase, side))
        c.leg(side, flex=1.5 * lift, knee=0.1 + 1.5 * lift, toes=0.3 * lift)
        c.arm(side, flex=0.5 * other - 0.1 * lift, abduct=0.2, elbow=0.3 + 0.8 * other)


def _shake_arms(c: _Clip) -> None:
    cycles, phase = c.uniform(3.0, 4.0), c.uniform(0, 1)
    c.torso(_rot(_Z, 0.05 * c.wave(cycles, phase)))
    for side in "LR":
        offset = 0.5 * (side == "R") + c.uniform(-0.1, 0.1)
        shake = c.wave(cycles, phase + offset, side) * c.side_amp[side] * c.amp
        flap = c.wave(cycles, phase + offset + 0.25, side) * c.side_amp[side] * c.amp
        c.arm(
            side,
            flex=0.35 + 0.15 * shake,
            abduct=0.35 + 0.1 * flap,
            internal=0.1 * flap,
            elbow=0.7 + 0.45 * flap,
        )
        c.clavicle(side, raise_=0.08 * shake)
        c.leg(side)


def _shake_hips(c: _Clip) -> None:
    cycles, phase = c.uniform(2.0, 3.0), c.uniform(0, 1)
    sway = c.wave(cycles, phase) * c.amp
    c.world["root"] = _rot(_Y, -0.12 * sway) @ _rot(_Z, 0.1 * c.wave(cycles, phase + 0.25))
    c.translation[:, 0] = 0.06 * sway
    c.translation[:, 2] = -0.04
    c.torso(_rot(_Y, 0.05 * sway))
    for side in "LR":
        c.planted_leg(side)
        c.arm(side, abduct=0.15 + 0.08 * sway * (1 if side == "L" else -1), elbow=0.4)


def _shake_shoulders(c: _Clip) -> None:
    cycles, phase = c.uniform(2.5, 4.0), c.uniform(0, 1)
    twist = 0.3 * c.amp * c.wave(cycles, phase)
    c.world["root"] = _rot(_Z, -0.2 * twist)
    c.torso(_rot(_Z, twist), head_follow=0.2)
    for side, sign in (("L", 1.0), ("R", -1.0)):
        w = sign * c.wave(cycles, phase, side) * c.side_amp[side]
        c.clavicle(side, raise_=0.3 * w, forward=-0.25 * w)
        c.arm(side, abduct=0.15, elbow=0.3)
        c.planted_leg(side)


def _running_on_spot(c: _Clip) -> None:
    cycles, phase = c.uniform(1.5, 2.2), c.uniform(0, 1)
    stride = c.wave(cycles, phase)
    c.translation[:, 2] = 0.05 * c.amp * (1 - stride**2)  # airborne as the legs cross
    c.torso(_rot(_X, 0.1))
    for side, sign in (("L", 1.0), ("R", -1.0)):
        w = (0.5 + 0.5 * sign * c.wave(cycles, phase, side)) ** 2 * c.side_amp[side] * c.amp
        c.leg(side, flex=1.0 * w**2, knee=0.2 + 1.6 * w, toes=0.4 * w)
        c.arm(side, flex=1.2 * (0.5 - w), abduct=0.15, elbow=1.5)


def _one_leg_pose(c: _Clip) -> tuple[str, str]:
    """Balance on one leg (chosen at random), arms out; returns (standing, free) sides."""
    standing, free = ("L", "R") if c.rng.random() < 0.5 else ("R", "L")
    for side in "LR":
        c.arm(side, flex=0.2, abduct=0.7 * c.side_amp[side], elbow=0.4)
    return standing, free


def _one_leg_jump(c: _Clip) -> None:
    cycles, phase = c.uniform(2.0, 3.0), c.uniform(0, 1)
    airborne = c.pulse(cycles, phase)
    c.torso(_EYE)
    standing, free = _one_leg_pose(c)
    drop = c.crouch(standing, 0.15 + 0.5 * (1 - airborne), toes=0.4 * airborne)
    c.leg(free, flex=0.5, knee=1.4 + 0.2 * airborne, toes=0.3)
    c.translation[:, 2] = 0.08 * c.amp * airborne - drop
    for side in "LR":
        c.clavicle(side, raise_=0.15 * airborne)


def _one_leg_loose(c: _Clip) -> None:
    cycles, phase = c.uniform(1.5, 2.5), c.uniform(0, 1)
    swing = c.wave(cycles, phase) * c.amp
    c.torso(_rot(_X, -0.05 * swing))
    standing, free = _one_leg_pose(c)
    c.translation[:, 2] = -c.crouch(standing, 0.2)
    c.leg(free, flex=0.3 + 0.45 * swing, knee=0.6 + 0.35 * c.wave(cycles, phase - 0.15), toes=0.3)


def _light_hopping(c: _Clip, loose: bool) -> None:
    cycles, phase = c.uniform(2.5, 3.5), c.uniform(0, 1)
    airborne = c.pulse(cycles, phase)
    c.torso(_rot(_X, 0.05 * c.wave(cycles, phase + 0.2)) if loose else _EYE, head_follow=0.3 if loose else 0.8)
    drops = []
    for side in "LR":
        knee = 0.15 + (0.5 if loose else 0.05) * (1 - airborne)
        drops.append(c.crouch(side, knee, toes=0.35 * airborne))
        if loose:
            flop = c.wave(cycles, phase + 0.3, side) * c.side_amp[side]
            c.arm(side, abduct=0.25 + 0.12 * flop, elbow=0.6 + 0.35 * flop)
        else:
            c.arm(side, abduct=0.12, elbow=0.15)
    c.translation[:, 2] = (0.05 if loose else 0.07) * c.amp * airborne - drops[0]


def _chicken_wings(c: _Clip) -> None:
    cycles, phase = c.uniform(2.0, 3.0), c.uniform(0, 1)
    c.torso(_EYE)
    for side in "LR":
        flap = c.pulse(cycles, phase, side) * c.side_amp[side] * c.amp
        c.arm(side, flex=0.05, abduct=0.3 + 0.8 * flap, internal=0.2, elbow=2.25)
        c.clavicle(side, raise_=0.12 * flap)
        c.planted_leg(side)


def _hips(c: _Clip) -> None:
    cycles, phase = c.uniform(1.0, 2.0), c.uniform(0, 1)
    along, across = c.wave(cycles, phase), c.wave(cycles, phase + 0.25)
    c.world["root"] = _rot(_Y, -0.12 * c.amp * along) @ _rot(_X, -0.12 * c.amp * across)
    c.translation[:, 0] = 0.05 * c.amp * along
    c.translation[:, 1] = 0.05 * c.amp * across
    c.translation[:, 2] = -0.03
    c.torso(_rot(_Y, 0.06 * along) @ _rot(_X, 0.06 * across))
    for side in "LR":
        c.planted_leg(side)
        c.arm(side, flex=-0.35, abduct=0.6, internal=0.8, elbow=1.8)  # hands on hips


def _jiggle_on_toes(c: _Clip) -> None:
    cycles, phase = c.uniform(3.0, 4.5), c.uniform(0, 1)
    rise = c.pulse(cycles, phase) * c.amp
    c.torso(_EYE, head_follow=0.5)
    drops = []
    for side in "LR":
        drops.append(c.crouch(side, 0.1 + 0.2 * (1 - rise), toes=0.5 * rise))
        c.arm(side, abduct=0.2 + 0.05 * c.wave(cycles, phase + 0.3, side), elbow=0.5)
    c.translation[:, 2] = 0.13 * torch.sin(0.5 * rise) - drops[0]


_PROGRAMS = {
    "jumping_jacks": _jumping_jacks,
    "punching": _punching,
    "knee_raises": _knee_raises,
    "shake_arms": _shake_arms,
    "shake_hips": _shake_hips,
    "shake_shoulders": _shake_shoulders,
    "running_on_spot": _running_on_spot,
    "one_leg_jump": _one_leg_jump,
    "one_leg_loose": _one_leg_loose,
    "light_hopping_stiff": lambda c: _light_hopping(c, loose=False),
    "light_hopping_loose": lambda c: _light_hopping(c, loose=True),
    "chicken_wings": _chicken_wings,
    "hips": _hips,
    "jiggle_on_toes": _jiggle_on_toes,
}
assert tuple(_PROGRAMS) == ACTIONS


def sample_motion(action: str, seed: int, bone_labels: list[str], frames: int = 30) -> Motion:
    """``frames`` evenly spaced poses of one randomised instance of ``action``.

    Deterministic in (action, seed, frames); ``bone_labels`` is ``BodyModel.bone_labels`` and
    must contain the controlled bones (any Anny topology of the default rig does).
    """
    if action not in _PROGRAMS:
        raise ValueError(f"unknown action {action!r}; valid: {list(ACTIONS)}")
    missing = [bone for bone in CONTROLLED_PARENTS if bone not in bone_labels]
    if missing:
        raise ValueError(f"bone_labels lack the controlled bones {missing}")
    clip = _Clip(seed, frames)
    _PROGRAMS[action](clip)
    identity = _EYE.expand(frames, 3, 3)
    for bone in CONTROLLED_PARENTS:
        clip.world.setdefault(bone, identity)
    clip.add_noise()
    # A random facing for the whole body: rotate every absolute rotation and the root offset.
    facing = _rot(_Z, clip.uniform(-0.15, 0.15))
    world = {bone: facing @ rotation for bone, rotation in clip.world.items()}
    translation = clip.translation @ facing[0].T
    return Motion(
        action=action,
        seed=seed,
        rotvecs=local_rotvecs(world, bone_labels).numpy().astype(np.float32),
        translation=translation.numpy().astype(np.float32),
    )


def local_rotvecs(world: dict[str, torch.Tensor], bone_labels: list[str]) -> torch.Tensor:
    """``(N, bones, 3)`` local rotation vectors for ``BodyModel.pose`` from the world rotations
    ``(N, 3, 3)`` of every controlled bone (D = Aₚᵀ A, Aₚ the nearest controlled ancestor's)."""
    n = next(iter(world.values())).shape[0]
    rotvecs = torch.zeros(n, len(bone_labels), 3, dtype=torch.float64)
    for bone, parent in CONTROLLED_PARENTS.items():
        local = world[bone] if parent is None else world[parent].transpose(-1, -2) @ world[bone]
        rotvecs[:, bone_labels.index(bone)] = roma.rotmat_to_rotvec(local)
    return rotvecs
