"""The Ray side of jobs/retarget.py: every target mesh x every driving clip as one graph of Ray tasks and actors.

- `load_target` / `load_clip` (tasks): each mesh file and each clip is read once, its up axis found and
  turned z up; the arrays stay in the object store, the driver gets only their topology (`num_returns=2`).
- `register_target` / `register_clip_task` (tasks): a target of another topology than the model runs on is
  registered once per topology, a clip of a foreign topology once; every pair that needs it gets the
  same `ObjectRef` (jobs/animate.py would register them again for every pair).
- `Animator` (actor): loads the checkpoint once, runs `aniformer.animation_run.infer` for each pair it is sent.
- `write_pair` (task): `aniformer.animation_outputs.write_animation` into ``OUT/<target stem>/<clip>/``, staged
  and renamed into place, in parallel with the next pairs' inference.

A worker killed mid-task costs only its tasks, retried (`MAX_RETRIES`); a killed actor is restarted and
its calls retried. A pair whose task raises (bad input, a failed registration) fails alone: its error
reaches the driver through the pair's last `ObjectRef`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import ray

from aniformer.animation_run import AnimateOptions
from pipeline.motion_library import ClipSource

MAX_RETRIES = 3  # a task whose worker died is run again this many times (never one that raised)


class Writable:
    """Arrays read from the object store are read-only views (torch warns of them, in-place code fails): a
    `Mesh` or `Clip` is unpickled with its own writable copies."""

    def __setstate__(self, state: dict) -> None:
        for name, value in state.items():
            object.__setattr__(self, name, np.array(value) if isinstance(value, np.ndarray) else value)


@dataclass(frozen=True)
class Mesh(Writable):
    """A target read once: z-up vertices in metres, faces, its (up axis, why) and (unit, why)."""

    path: str
    vertices: np.ndarray
    faces: np.ndarray
    axis: tuple[str, str]
    unit: tuple[str, str]


@dataclass(frozen=True)
class Clip(Writable):
    """A driving clip read once: z-up frames (T, V, 3) in metres, faces, fps, (up axis, why), (unit, why), and the
    glTF animation it was played from, if it is one file (`aniformer.io.gltf_scene.GltfClip.record`)."""

    path: str
    driving: np.ndarray
    faces: np.ndarray
    fps: float
    axis: tuple[str, str]
    unit: tuple[str, str]
    animation: dict | None


@dataclass(frozen=True)
class Refused:
    """A pair whose result the self-check does not trust (written only with --force)."""

    reason: str


@ray.remote(num_returns=2, max_retries=MAX_RETRIES)
def load_target(path: str, up: str, unit: str, max_vertices: int):
    """(its Anny topology or None, the `Mesh`)."""
    from aniformer.animation_run import anny_topology, input_axis
    from aniformer.geometry import to_z_up
    from aniformer.io.mesh import load_body_mesh

    vertices, faces, unit = load_body_mesh(path, max_vertices, unit)
    axis = input_axis(up, Path(path), vertices[None], faces)
    vertices = to_z_up(vertices, axis[0])
    return anny_topology(vertices, faces), Mesh(path, vertices, faces, axis, unit)


@ray.remote(num_returns=2, max_retries=MAX_RETRIES)
def load_clip(path: str, animation: str | None, up: str, unit: str, max_vertices: int, max_frames: int,
              trained_topology: str):
    """({"frames", "anny": its Anny topology or None, "topology": the one the model runs on for it}, the `Clip` of
    ``path``'s frames, or of its glTF ``animation``)."""
    from aniformer.animate import driving_clip, driving_files, driving_fps, driving_frames, driving_unit, load_driving
    from aniformer.animation_run import anny_topology, input_axis
    from aniformer.errors import UserError
    from aniformer.geometry import to_z_up

    files = driving_files(path)
    clip = driving_clip(files, animation=animation)
    frames = driving_frames(files, clip)
    if frames > max_frames:
        raise UserError(f"{path}: {frames:,} frames exceeds --max-frames {max_frames:,}")
    unit = driving_unit(files, clip, max_vertices, unit)
    driving, faces = load_driving(files, max_vertices, unit[0], clip=clip)
    axis = input_axis(up, files[0], driving, faces)
    driving = to_z_up(driving, axis[0])
    anny = anny_topology(driving[0], faces)
    # the topology the model runs on for this clip, as aniformer.animation_run.model_inputs chooses it
    info = {"frames": len(driving), "anny": anny, "topology": anny or trained_topology}
    return info, Clip(path, driving, faces, driving_fps(files, clip) or 30.0, axis, unit,
                      clip.record() if clip is not None else None)


@ray.remote(num_returns=2, max_retries=MAX_RETRIES)
def register_target(mesh: Mesh, topology: str):
    """(the target's `Correspondence` on ``topology``, {"rms_m", "seconds"})."""
    from aniformer.correspondence import register_mesh

    began = time.perf_counter()
    fit = register_mesh(mesh.vertices, mesh.faces, topology)
    return fit, {"rms_m": fit.rms, "seconds": time.perf_counter() - began}


@ray.remote(num_returns=2, max_retries=MAX_RETRIES)
def register_clip_task(clip: Clip, topology: str):
    """((the clip's `Correspondence`, its `Trust`), {"rms_m", "seconds"}): registered on the whole clip."""
    from aniformer.correspondence import register_clip

    began = time.perf_counter()
    fit, trust = register_clip(clip.driving, clip.faces, topology)
    return (fit, trust), {"rms_m": fit.rms, "seconds": time.perf_counter() - began}


# num_cpus=0: inference is a small share of a pair's work (registration and writing are the rest); an actor
# holding a CPU would leave it idle while those tasks queue for it (docs/retarget.md)
@ray.remote(num_cpus=0, max_restarts=2, max_task_retries=2)
class Animator:
    """The model, loaded once from the checkpoint's bytes (the driver's file need not exist on this node) at
    the first pair: a restarted actor (its worker killed) loads it again at its next one."""

    def __init__(self):
        self.model = self.state = self.device = None

    def _load(self, checkpoint: bytes | None) -> None:
        """The model of the checkpoint's bytes; None: the skinned transfer, no network."""
        import tempfile

        from aniformer.checkpoint import model_from_checkpoint
        from aniformer.cli.args import resolve_device
        from aniformer.skinned_transfer import skinned_model

        if checkpoint is None:
            self.model, self.state = skinned_model()
        else:
            with tempfile.NamedTemporaryFile(suffix=".pt") as file:
                file.write(checkpoint)
                file.flush()
                self.model, self.state = model_from_checkpoint(file.name)
        self.device = resolve_device("auto")

    def animate(self, checkpoint: list[ray.ObjectRef], options: AnimateOptions, target: Mesh, clip: Clip, target_fit,
                driver_fit):
        """`aniformer.animation_run.infer` for one pair (``options``: its animate options) with the shared
        registrations: (the inference tuple, seconds), or `Refused`. ``checkpoint``: [its bytes' ref],
        fetched at the first call only."""
        import copy

        from aniformer.animation_run import check_glb_size, infer

        if self.model is None:
            self._load(ray.get(checkpoint[0]))
        target_fit, driver_fit = copy.deepcopy((target_fit, driver_fit))  # writable arrays (see `Writable`)
        check_glb_size(options, len(clip.driving), target.vertices, target.faces)
        registered = {role: fit for role, fit in (("target", target_fit), ("driver", driver_fit)) if fit is not None}
        seconds = {}
        began = time.perf_counter()
        inference = infer(options, self.model, self.state, clip.driving, clip.faces, target.vertices, target.faces,
                          self.device, seconds, registered)
        seconds["inference"] = round(time.perf_counter() - began, 3)
        if not inference.trust.ok and not options.force:
            return Refused(inference.trust.reason())
        return inference, seconds


@ray.remote(max_retries=MAX_RETRIES)
def write_pair(options: AnimateOptions, out: Path, state: dict, target: Mesh, clip: Clip, animated) -> dict:
    """Write one pair's outputs into ``out`` (`aniformer.animation_outputs.write_animation`); its summary row."""
    if isinstance(animated, Refused):
        return {"status": "refused", "self_check": animated.reason}
    if (out / "animation.json").is_file():  # a retry after the attempt that wrote it died
        return pair_row(out, "ok")
    import copy

    from aniformer.animation_outputs import write_animation

    inference, seconds = animated
    # writable arrays for the rig's fit (see `Writable`)
    inference = replace(inference, registrations=copy.deepcopy(inference.registrations))
    began = time.perf_counter()
    name = f"{Path(target.path).stem}_{Path(clip.path).stem if clip.animation else Path(clip.path).name}"
    write_animation(out, options, state, name, clip.fps, clip.driving, clip.faces, target.vertices, target.faces,
                    {"target": target.axis, "driver": clip.axis}, {"target": target.unit, "driver": clip.unit},
                    inference, seconds, driving_animation=clip.animation)
    return pair_row(out, "ok", seconds["inference"] + time.perf_counter() - began)


def pair_row(out: Path, status: str, seconds: float | None = None) -> dict:
    """A pair's summary row from its animation.json: frames, fit error (the worst registration's RMS, mm),
    the self-check (trusted, with its check nearest its limit, or why not), seconds of its own work."""
    import json

    summary = json.loads((out / "animation.json").read_text())
    fits = [fit["rms_m"] * 1000 for fit in summary["registered"].values()]
    checks = summary["trust"]["checks"]
    worst = max(checks, key=lambda c: c["value"] / c["limit"])
    verdict = "trusted" if summary["trust"]["ok"] else "not trusted (--force)"
    return {"status": status, "frames": summary["frames"], "seconds": "" if seconds is None else round(seconds, 2),
            "fit_mm": f"{max(fits):.1f}" if fits else "",
            "self_check": f"{verdict}, nearest limit: {worst['name']} {worst['value']:.3f} of {worst['limit']:.3f}"}


def error_line(error: BaseException) -> str:
    """The one-line reason of a pair's failure: the task's own exception, not Ray's traceback around it."""
    cause = error.cause if isinstance(error, ray.exceptions.RayTaskError) and error.cause is not None else error
    lines = [line.strip() for line in str(cause).splitlines() if line.strip()]
    from aniformer.errors import UserError

    text = lines[0] if lines else ""
    return text if isinstance(cause, UserError) else f"{type(cause).__name__}: {text}".rstrip(": ")


@dataclass(frozen=True)
class Pair:
    target: str  # the target's file stem
    clip: str  # the clip's folder name
    out: Path  # OUT/<target stem>/<clip>/
    options: AnimateOptions  # jobs/animate.py's options for this pair alone


def schedule(pairs: list[Pair], targets: dict[str, str], clips: dict[str, ClipSource], options: dict,
             checkpoint: bytes | None, state: dict, registers: bool, actors: int, events):
    """Submit the whole graph for ``pairs`` (``targets``: name -> path, ``clips``: name -> source; ``options``: up, unit,
    max_vertices, max_frames; ``checkpoint``: its bytes, None for the skinned transfer) and yield ``(pair, row)``
    as each pair finishes, row["status"] ok, refused or error (with "error", one line). Each registration is
    reported to ``events(line)`` once it is made."""
    trained = (state["config"].get("data") or {}).get("topology")
    common = (options["up"], options["unit"], options["max_vertices"])
    target_refs = {name: load_target.remote(path, *common) for name, path in targets.items()
                   if any(p.target == name for p in pairs)}
    clip_refs = {name: load_clip.remote(source.path, source.animation, *common, options["max_frames"], trained)
                 for name, source in clips.items()
                 if any(p.clip == name for p in pairs)}
    target_topology, clip_info, failed = {}, {}, {}
    for name, (info, _) in target_refs.items():
        try:
            target_topology[name] = ray.get(info)
        except Exception as error:  # a bad mesh fails its own pairs only
            failed[("target", name)] = error_line(error)
    for name, (info, _) in clip_refs.items():
        try:
            clip_info[name] = ray.get(info)
        except Exception as error:
            failed[("clip", name)] = error_line(error)

    # the actors first, so that they start while the meshes load
    checkpoint_ref, state_ref = ray.put(checkpoint), ray.put(state)
    animators = [Animator.remote() for _ in range(actors)]
    target_fits, clip_fits, reports = {}, {}, {}
    ready, waiting = [], []
    for pair in pairs:
        reason = failed.get(("target", pair.target)) or failed.get(("clip", pair.clip))
        if reason:
            yield pair, {"status": "error", "error": reason}
            continue
        topology = clip_info[pair.clip]["topology"]
        target_fit = driver_fit = None
        if registers and target_topology[pair.target] != topology:
            key = (pair.target, topology)
            if key not in target_fits:
                target_fits[key], report = register_target.remote(target_refs[pair.target][1], topology)
                reports[report] = f"target {pair.target} onto Anny {topology}"
            target_fit = target_fits[key]
        if registers and clip_info[pair.clip]["anny"] is None:
            if pair.clip not in clip_fits:
                clip_fits[pair.clip], report = register_clip_task.remote(clip_refs[pair.clip][1], topology)
                reports[report] = f"clip {pair.clip} onto Anny {topology}"
            driver_fit = clip_fits[pair.clip]
        # pairs that wait for no registration go first: an actor runs its calls in the order they were sent
        (ready if target_fit is None and driver_fit is None else waiting).append((pair, target_fit, driver_fit))
    finals = {}
    for k, (pair, target_fit, driver_fit) in enumerate(ready + waiting):
        target, clip = target_refs[pair.target][1], clip_refs[pair.clip][1]
        # the checkpoint's ref in a list: fetched by the actor at its first pair, not sent with every call
        animated = animators[k % actors].animate.remote([checkpoint_ref], pair.options, target, clip, target_fit,
                                                        driver_fit)
        finals[write_pair.remote(pair.options, pair.out, state_ref, target, clip, animated)] = pair
    while finals or reports:
        done, _ = ray.wait([*finals, *reports], num_returns=1)
        ref = done[0]
        if ref in reports:
            what = reports.pop(ref)
            try:
                fit = ray.get(ref)
                events(f"registered {what}: {fit['rms_m'] * 1000:.1f} mm RMS surface distance, {fit['seconds']:.1f} s")
            except Exception as error:  # its pairs report it too
                events(f"registration of {what} failed: {error_line(error)}")
            continue
        pair = finals.pop(ref)
        try:
            yield pair, ray.get(ref)
        except Exception as error:  # one pair's failure is its row, the others go on
            yield pair, {"status": "error", "error": error_line(error)}
