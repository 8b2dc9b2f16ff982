"""Procedural DFAUST-like motions for the Anny rig.

No motion capture ships with Anny, so each action class is a small program: periodic joint
angles with randomised amplitude, tempo (cycles per clip), phase, left/right asymmetry and
smooth per-joint noise, all drawn from ``np.random.default_rng(seed)``. A clip is ``frames``
evenly spaced samples of one continuous motion, like the paper's 30 frames per DFAUST clip.
The programs pose the rig in world space through ``rig._Clip`` (axes and angles: see ``rig``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from aniformer.synth.rig import _EYE, _X, _Y, _Z, CONTROLLED_PARENTS, _Clip, _rot, local_rotvecs

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


@dataclass(frozen=True)
class Motion:
    """One sampled clip: per-frame local bone rotations and root offset for ``BodyModel.pose``."""

    action: str
    seed: int
    rotvecs: np.ndarray  # (frames, bone_count, 3) float32
    translation: np.ndarray  # (frames, 3) float32, metres


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
