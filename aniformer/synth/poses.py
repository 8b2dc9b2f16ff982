"""Smooth motion windows over the whole pose space, made in batches: the on-the-fly training data.

The procedural library (``motions``) holds 14 upright DFAUST-like actions; real motion capture
also walks, turns, crouches, kneels, bends, reaches in every direction and lies or flips over. A
*window* here is ``T`` consecutive frames of one smooth motion, drawn from a *family*:

    random       every controlled joint moves smoothly within its anatomical range (the
                 NPT-style random pose, but continuous in time)
    bend         large torso bends and twists, arms anywhere, legs near standing
    crouch       deep squats and kneeling (deep hip and knee flexion), arms anywhere
    locomotion   walking and running gaits that turn and travel (root motion)
    library      a window of a procedural action (``motions.ACTIONS``) at a random speed
    blend        a library window whose arms or legs come from a ``random`` window
    kick         front kicks with a chambered knee and a guard (evaluation only: no other
                 family bends a leg that way, so it measures an unseen action family)

and an *orientation*: ``upright`` (any heading), ``tilted`` (up to 90 degrees from vertical:
leaning, falling, lying) or ``any`` (uniform over SO(3), upside down included); half of the
windows also turn at a constant angular velocity. Locomotion stays upright with its own turning.

Every row of a batch is a pure function of its own ``numpy.random.Generator``: the batch only
vectorises the arithmetic. Joint angles follow ``mid + half * sin(u0 + a * sin(2 pi f t + phi))``,
which stays inside ``[mid - half, mid + half]``, is smooth, and dwells near the limits as real
extreme poses do; ``f`` (cycles per frame) times a per-window speed sets realistic tempos.
Angles are the anatomical ones of ``rig._Clip`` (radians, left side; the right side mirrors).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np
import roma
import torch

from aniformer.synth.motions import ACTIONS, sample_motion
from aniformer.synth.rig import _EYE, _X, _Y, _Z, CONTROLLED_PARENTS, _Clip, _rot, local_rotvecs

FAMILIES: tuple[str, ...] = ("random", "bend", "crouch", "locomotion", "library", "blend", "kick")
ORIENTATIONS: tuple[str, ...] = ("upright", "tilted", "any")
LIBRARY_FRAMES = 60  # frames of a cached library clip; windows are taken from it at stride 1-3
LIBRARY_INSTANCES = 64  # distinct instances per action (a cache of clips, not of windows)

# (low, high) per joint angle. Left side; the right side gets the same limits (mirrored).
_LIMB_LIMITS = {
    "arm_flex": (-0.9, 3.0), "arm_abduct": (-0.3, 2.8), "arm_internal": (-1.2, 1.2), "elbow": (0.0, 2.6),
    "clav_raise": (-0.1, 0.4), "clav_forward": (-0.3, 0.4),
    "leg_flex": (-0.5, 2.2), "leg_abduct": (-0.3, 0.9), "leg_internal": (-0.6, 0.6), "knee": (0.0, 2.4),
    "toes": (-0.4, 0.8),
}
_TORSO_LIMITS = {"bend": (-0.4, 0.9), "side": (-0.4, 0.4), "twist": (-0.6, 0.6), "nod": (-0.5, 0.7),
                 "turn": (-1.0, 1.0)}
_WIDE_TORSO = {"bend": (-0.6, 1.5), "side": (-0.8, 0.8), "twist": (-1.1, 1.1)}
_STANDING_LEGS = {"leg_flex": (-0.2, 0.4), "leg_abduct": (-0.05, 0.3), "leg_internal": (-0.3, 0.3),
                  "knee": (0.0, 0.5), "toes": (-0.2, 0.4)}
_ARM_KEYS = ("arm_flex", "arm_abduct", "arm_internal", "elbow", "clav_raise", "clav_forward")
_LEG_KEYS = ("leg_flex", "leg_abduct", "leg_internal", "knee", "toes")
_ARM_BONES = ("clavicle", "upperarm01", "lowerarm01")
_LEG_BONES = ("upperleg01", "lowerleg01", "foot")


def _smooth(rngs: Sequence[np.random.Generator], limits: dict, T: int, speed: np.ndarray) -> dict[str, torch.Tensor]:
    """Per joint, ``(B * T,)`` angles: a smooth trajectory inside its limits for every row."""
    keys = list(limits)
    draws = np.stack([rng.random((len(keys), 4)) for rng in rngs])  # (B, J, 4)
    t = np.arange(T)[None, :, None]
    u0, amplitude = 2 * np.pi * draws[:, None, :, 0], 1.5 * draws[:, None, :, 1]
    cycles = (0.005 + 0.045 * draws[:, None, :, 2]) * speed[:, None, None]
    phase = 2 * np.pi * draws[:, None, :, 3]
    wave = np.sin(u0 + amplitude * np.sin(2 * np.pi * cycles * t + phase))  # (B, T, J)
    low, high = (np.array([limits[k][i] for k in keys]) for i in (0, 1))
    angles = (low + high) / 2 + (high - low) / 2 * wave
    return {k: torch.from_numpy(angles[..., j].reshape(-1)) for j, k in enumerate(keys)}


def _sided(limits: dict, keys: Sequence[str]) -> dict:
    return {f"{k}.{side}": limits[k] for side in "LR" for k in keys}


def _pose_limbs(clip: _Clip, angles: dict[str, torch.Tensor], arms: bool = True, legs: bool = True) -> None:
    for side in "LR":
        a = {k: angles[f"{k}.{side}"] for k in (*(_ARM_KEYS if arms else ()), *(_LEG_KEYS if legs else ()))}
        if arms:
            clip.clavicle(side, raise_=a["clav_raise"], forward=a["clav_forward"])
            clip.arm(side, flex=a["arm_flex"], abduct=a["arm_abduct"], internal=a["arm_internal"], elbow=a["elbow"])
        if legs:
            clip.leg(side, flex=a["leg_flex"], abduct=a["leg_abduct"], knee=a["knee"], toes=a["toes"],
                     internal=a["leg_internal"])


def _pose_torso(clip: _Clip, angles: dict[str, torch.Tensor]) -> None:
    clip.torso(_rot(_Z, angles["twist"]) @ _rot(_Y, angles["side"]) @ _rot(_X, angles["bend"]))
    clip.world["head"] = clip.world["head"] @ _rot(_Z, angles["turn"]) @ _rot(_X, angles["nod"])


def _body_windows(rngs, T: int, speed: np.ndarray, torso: dict, legs: dict) -> _Clip:
    """Arms anywhere, torso and legs within the given limits: the random and bend families."""
    clip = _Clip(0, len(rngs) * T)
    limits = {**_sided(_LIMB_LIMITS, _ARM_KEYS), **_sided({**_LIMB_LIMITS, **legs}, _LEG_KEYS),
              **{**_TORSO_LIMITS, **torso}}
    angles = _smooth(rngs, limits, T, speed)
    _pose_torso(clip, angles)
    _pose_limbs(clip, angles)
    return clip


def _random(rngs, T, speed):
    return _body_windows(rngs, T, speed, {}, {})


def _bend(rngs, T, speed):
    return _body_windows(rngs, T, speed, _WIDE_TORSO, _STANDING_LEGS)


def _per_row(rngs, T: int, low: float, high: float) -> torch.Tensor:
    """One uniform value per row, repeated over its T frames: ``(B * T,)``."""
    return torch.from_numpy(np.repeat([rng.uniform(low, high) for rng in rngs], T))


def _crouch(rngs, T, speed):
    """Squats (depth varying smoothly) or kneeling on one knee, the torso leaning to balance."""
    clip = _Clip(0, len(rngs) * T)
    angles = _smooth(rngs, {**_sided(_LIMB_LIMITS, _ARM_KEYS), **_TORSO_LIMITS,
                            "depth": (0.35, 1.0), "spread": (0.0, 0.5)}, T, speed)
    kneel = torch.from_numpy(np.repeat([rng.random() < 0.4 for rng in rngs], T))
    kneel_side = np.repeat([rng.random() < 0.5 for rng in rngs], T)
    depth, lean = angles["depth"], _per_row(rngs, T, 0.3, 0.8)
    angles["bend"] = lean * depth + 0.3 * (angles["bend"] - 0.25)
    _pose_torso(clip, angles)
    _pose_limbs(clip, angles, legs=False)
    hip_share = _per_row(rngs, T, 0.45, 0.75)
    for side in "LR":
        squat_knee = 2.4 * depth
        down = torch.from_numpy(kneel_side == (side == "L"))  # the leg whose knee is on the ground
        knee = torch.where(kneel, torch.where(down, 1.3 + 0.5 * depth, 1.2 + 0.5 * depth), squat_knee)
        flex = torch.where(kneel, torch.where(down, -0.2 + 0.4 * depth, 1.1 + 0.5 * depth), hip_share * squat_knee)
        abduct = torch.where(kneel, torch.full_like(depth, 0.1), 0.1 + angles["spread"])
        clip.leg(side, flex=flex, abduct=abduct, knee=knee, toes=torch.where(kneel & down, 0.6, -0.2 * depth))
    clip.translation[:, 2] = -0.5 * depth
    return clip


def _gait(rngs, T: int, speed: np.ndarray):
    """(phase (B*T,), running (B*T,) bool, heading (B*T,)) of walking or running windows."""
    B = len(rngs)
    start = np.array([rng.uniform(0, 2 * np.pi) for rng in rngs])
    rate = np.array([rng.uniform(0.12, 0.45) for rng in rngs]) * speed  # gait phase per frame
    turn = np.array([rng.uniform(-0.08, 0.08) for rng in rngs])  # heading change per frame
    heading0 = np.array([rng.uniform(0, 2 * np.pi) for rng in rngs])
    running = np.repeat([rng.random() < 0.4 for rng in rngs], T)
    t = np.arange(T)[None]
    phase = (start[:, None] + rate[:, None] * t).reshape(-1)
    heading = (heading0[:, None] + turn[:, None] * t).reshape(-1)
    return torch.from_numpy(phase), torch.from_numpy(running), torch.from_numpy(heading), rate, B


def _locomotion(rngs, T, speed):
    """Walking or running gaits built facing -y, then turned to each frame's heading."""
    clip = _Clip(0, len(rngs) * T)
    phase, running, heading, rate, B = _gait(rngs, T, speed)
    stride = torch.where(running, _per_row(rngs, T, 0.5, 0.9), _per_row(rngs, T, 0.3, 0.55))
    clip.torso(_rot(_Z, 0.12 * torch.sin(phase)) @ _rot(_X, torch.where(running, 0.2, 0.05)))
    for side, shift in (("L", 0.0), ("R", np.pi)):
        swing = torch.sin(phase + shift)
        knee = 0.1 + torch.where(running, 1.5, 0.7) * torch.sin(phase + shift + 1.2).clamp(min=0)
        clip.leg(side, flex=stride * swing + torch.where(running, 0.3, 0.05), abduct=torch.full_like(phase, 0.05),
                 knee=knee, toes=0.3 * torch.sin(phase + shift - 0.8).clamp(min=0))
        clip.clavicle(side)
        clip.arm(side, flex=-0.8 * stride * swing, abduct=torch.full_like(phase, 0.15),
                 elbow=torch.where(running, 1.5, 0.35))
    turn = _rot(_Z, heading)
    clip.world = {bone: turn @ rotation for bone, rotation in clip.world.items()}
    clip.world.setdefault("root", turn)
    step = torch.from_numpy(np.repeat(rate, T)) / (2 * np.pi) * torch.where(running, 2.2, 1.4)  # metres per frame
    forward = torch.stack([torch.sin(heading), -torch.cos(heading), torch.zeros_like(heading)], -1)
    travelled = torch.cumsum((step[:, None] * forward).reshape(B, T, 3), dim=1).reshape(-1, 3)
    bounce = torch.where(running, 0.05, 0.015) * torch.sin(2 * phase).abs()
    clip.translation = travelled + torch.stack([torch.zeros_like(phase), torch.zeros_like(phase), bounce], -1)
    return clip


def _kick(rngs, T, speed):
    clip = _Clip(0, len(rngs) * T)
    start = np.array([rng.uniform(0, 2 * np.pi) for rng in rngs])
    rate = np.array([rng.uniform(0.15, 0.5) for rng in rngs]) * speed
    phase = torch.from_numpy((start[:, None] + rate[:, None] * np.arange(T)[None]).reshape(-1))
    kicking = np.repeat([rng.random() < 0.5 for rng in rngs], T)
    height = _per_row(rngs, T, 1.1, 2.0)
    lift = 0.5 - 0.5 * torch.cos(phase)  # 0 -> 1 -> 0 per kick
    extend = torch.sin(phase).clamp(max=0).neg()  # the knee opens in the second half of the lift
    clip.torso(_rot(_X, -0.35 * lift))
    for side in "LR":
        clip.arm(side, flex=torch.full_like(phase, 0.8), abduct=torch.full_like(phase, 0.35), elbow=torch.full_like(phase, 2.1))
        clip.clavicle(side, forward=torch.full_like(phase, 0.15))
        kick_side = torch.from_numpy(kicking == (side == "L"))
        clip.leg(side, flex=torch.where(kick_side, height * lift, 0.15),
                 knee=torch.where(kick_side, 1.9 * lift * (1 - extend), 0.3),
                 abduct=torch.full_like(phase, 0.08), toes=torch.where(kick_side, 0.6 * lift, 0.0))
    return clip


_PROGRAMS = {"random": _random, "bend": _bend, "crouch": _crouch, "locomotion": _locomotion, "kick": _kick}


@functools.lru_cache(maxsize=4096)
def _library_clip(action: str, instance: int, bone_labels: tuple[str, ...]):
    return sample_motion(action, 1_000_003 * ACTIONS.index(action) + instance, list(bone_labels), frames=LIBRARY_FRAMES)


def _library(rngs, T: int, bone_labels, actions: Sequence[str]):
    """Library windows: (B*T, bones, 3) rotvecs and (B*T, 3) translations (stride 1-3 frames; a window too long
    for stride 3 within a clip's ``LIBRARY_FRAMES`` takes the strides that fit)."""
    longest = 3 if T == 1 else min(3, (LIBRARY_FRAMES - 1) // (T - 1))
    if longest < 1:
        raise ValueError(f"library windows hold at most {LIBRARY_FRAMES} frames, not {T}")
    rotvecs, translation = [], []
    for rng in rngs:
        clip = _library_clip(actions[rng.integers(len(actions))], int(rng.integers(LIBRARY_INSTANCES)), tuple(bone_labels))
        stride = int(rng.integers(1, longest + 1))
        start = int(rng.integers(LIBRARY_FRAMES - (T - 1) * stride))
        rows = slice(start, start + (T - 1) * stride + 1, stride)
        rotvecs.append(clip.rotvecs[rows])
        translation.append(clip.translation[rows])
    return torch.from_numpy(np.concatenate(rotvecs)).double(), torch.from_numpy(np.concatenate(translation)).double()


def _clip_rotvecs(clip: _Clip, bone_labels) -> torch.Tensor:
    identity = _EYE.expand(clip.frames, 3, 3)
    world = {bone: clip.world.get(bone, identity) for bone in CONTROLLED_PARENTS}
    return local_rotvecs(world, list(bone_labels))


def _orientations(rngs, modes: Sequence[str], T: int) -> torch.Tensor:
    """``(B * T, 3, 3)`` global rotations: a start orientation of each row's mode, turning at a
    constant angular velocity in half of the rows."""
    starts, spins = [], []
    for rng, mode in zip(rngs, modes, strict=True):
        yaw = roma.rotvec_to_rotmat(torch.tensor([0.0, 0.0, rng.uniform(0, 2 * np.pi)], dtype=torch.float64))
        if mode == "upright":
            start = yaw
        elif mode == "tilted":
            axis = rng.uniform(0, 2 * np.pi)
            tilt = torch.tensor([np.cos(axis), np.sin(axis), 0.0]) * rng.uniform(0, np.pi / 2)
            start = roma.rotvec_to_rotmat(tilt.double()) @ yaw
        else:
            quat = torch.from_numpy(rng.normal(size=4))
            start = roma.unitquat_to_rotmat(quat / quat.norm())
        axis = rng.normal(size=3)
        rate = rng.uniform(0, 0.12) if rng.random() < 0.5 else 0.0
        starts.append(start)
        spins.append(axis / np.linalg.norm(axis) * rate)
    start = torch.stack(starts).repeat_interleave(T, 0)
    t = torch.arange(T, dtype=torch.float64).repeat(len(rngs))[:, None]
    spin = torch.from_numpy(np.stack(spins)).repeat_interleave(T, 0) * t
    return roma.rotvec_to_rotmat(spin) @ start


def _orient(rotvecs: torch.Tensor, translation: torch.Tensor, rotation: torch.Tensor, root: int):
    """Rotate whole bodies: the root's rotation and the root offset (every other bone is relative)."""
    rotvecs = rotvecs.clone()
    rotvecs[:, root] = roma.rotmat_to_rotvec(rotation @ roma.rotvec_to_rotmat(rotvecs[:, root]))
    return rotvecs, (rotation @ translation[..., None])[..., 0]


def sample_windows(families: Sequence[str], orientations: Sequence[str], rngs: Sequence[np.random.Generator], T: int,
                   bone_labels: Sequence[str], actions: Sequence[str] = ACTIONS,
                   speed_range: tuple[float, float] = (0.5, 2.0)) -> tuple[np.ndarray, np.ndarray]:
    """Windows of ``T`` frames, one per rng: rotvecs ``(B, T, bones, 3)`` and translations
    ``(B, T, 3)`` float32 for ``BodyModel.pose``. Row ``b`` is of family ``families[b]``,
    orientation ``orientations[b]`` and a function of ``rngs[b]`` alone; ``actions`` are the
    library actions the ``library`` and ``blend`` families may use."""
    unknown = sorted(set(families) - set(FAMILIES)) + sorted(set(orientations) - set(ORIENTATIONS))
    if unknown:
        raise ValueError(f"unknown families or orientations {unknown}; families: {FAMILIES}, orientations: {ORIENTATIONS}")
    B, bones = len(rngs), len(bone_labels)
    rotvecs = torch.zeros(B, T, bones, 3, dtype=torch.float64)
    translation = torch.zeros(B, T, 3, dtype=torch.float64)
    speed = np.exp(np.array([rng.uniform(*np.log(speed_range)) for rng in rngs]))
    families = np.asarray(families)
    for family in np.unique(families):
        rows = np.flatnonzero(families == family)
        sub = [rngs[i] for i in rows]
        if family in ("library", "blend"):
            r, tr = _library(sub, T, bone_labels, actions)
            if family == "blend":  # arms or legs of a random window, relative to their parents
                donor = _clip_rotvecs(_random(sub, T, speed[rows]), bone_labels)
                arms = np.repeat([rng.random() < 0.5 for rng in sub], T)
                for side in "LR":
                    for bone in (*_ARM_BONES, *_LEG_BONES):
                        take = torch.from_numpy(arms if bone in _ARM_BONES else ~arms)
                        j = list(bone_labels).index(f"{bone}.{side}")
                        r[take, j] = donor[take, j]
        else:
            clip = _PROGRAMS[family](sub, T, speed[rows])
            r, tr = _clip_rotvecs(clip, bone_labels), clip.translation
        rotvecs[rows], translation[rows] = r.reshape(len(rows), T, bones, 3), tr.reshape(len(rows), T, 3)
    turning = np.flatnonzero(families != "locomotion")
    if len(turning):
        rotation = _orientations([rngs[i] for i in turning], [orientations[i] for i in turning], T)
        r, tr = _orient(rotvecs[turning].reshape(-1, bones, 3), translation[turning].reshape(-1, 3), rotation,
                        list(bone_labels).index("root"))
        rotvecs[turning], translation[turning] = r.reshape(len(turning), T, bones, 3), tr.reshape(len(turning), T, 3)
    return rotvecs.numpy().astype(np.float32), translation.numpy().astype(np.float32)
