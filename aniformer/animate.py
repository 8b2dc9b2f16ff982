"""Animate a target mesh with a driving sequence of any length (the GLB writer is ``aniformer.io.glb``).

Sliding window
--------------
A model sees T frames at a time (``model.config.window``). ``animate_sequence`` slides a T-frame
window over the driving sequence one frame at a time and batches the windows. How the overlapping
predictions combine (``combine``):

- ``"mean"`` (default, heads that predict every frame of a window): windows start at frames
  0 .. N-T, so frame t is predicted by every window that contains it (up to T of them: fewer
  near the ends) and its output is the plain average of those predictions.
- ``"center"``: each frame takes the one prediction of the window centred on it. The sequence is
  padded at both ends by repeating its first / last frame (T//2 in front, T-1-T//2 behind) so the
  edge frames have a centred window too. The regression head (which predicts only the centre frame
  of a window, ``config.output_frames()``) always combines this way.

A sequence shorter than T is padded at the end by repeating its last frame.

Huge meshes: attention is linear in memory but quadratic in time with the vertex count. Before the
first window, ``animate_sequence`` estimates the inference time from the model's FLOP count
(``forward_flops``) and a matrix product timed on the device (``matmul_flops_per_second``). Above
``WARN_SECONDS`` it warns on stderr, above ``REFUSE_SECONDS`` it refuses unless ``force``; both
give the estimate and point to decimating the target first.

Centring: every driving frame and the target are bounding-box centred like the training pairs
(``center="mesh"``; ``"window"`` centres each window as a whole, ``"none"`` not at all: use the
checkpoint's ``data.center``). The model outputs centred meshes; ``root_motion`` gives the
translation that puts each output frame where the driver is (world space).
"""

from __future__ import annotations

import glob
import json
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from aniformer.errors import MeshError, UserError
from aniformer.geometry import CENTER_MODES, center_bbox
from aniformer.io.files import natural_key
from aniformer.io.gltf_scene import GltfClip, gltf_clip
from aniformer.io.mesh import DEFAULT_MAX_VERTICES, MESH_SUFFIXES, UNITS, body_unit, load_body_mesh, load_mesh, validate_mesh

if TYPE_CHECKING:  # torch and trimesh load in the functions that use them: jobs' --help and input checks stay fast
    import torch

COMBINE_RULES = ("mean", "center")
# Estimated inference times beyond which `animate_sequence` warns, and refuses unless `force`.
WARN_SECONDS = 10 * 60
REFUSE_SECONDS = 2 * 3600
DECIMATE_HINT = ("decimate the target first (trimesh's simplify_quadric_decimation, as "
                 "aniformer.synth.variants.remesh does; bench/remesh_sample.py shows it on a sample)")
MIN_CHECKED_FLOPS = 1e12  # below: under a minute even on 2 CPU cores; not worth timing a matrix product
_MATMUL_RATES: dict[str, float] = {}  # device -> measured FLOP/s, once per process


# --------------------------------------------------------------------------------------------
# Inference time of huge meshes
# --------------------------------------------------------------------------------------------


def matmul_flops_per_second(device: str | torch.device) -> float:
    """FLOP/s of a float32 matrix product on `device`: the best of 6 timed products, once per process
    (well under a second on 2 CPU cores). The model's layers reach less (2 shared CPU cores: 60-100
    GFLOP/s for the product, 23-74 for windows of 20,000-163,842 vertices), so times estimated from it
    are lower bounds."""
    import torch

    device = torch.device(device)
    if str(device) not in _MATMUL_RATES:
        n = 2048 if device.type == "cuda" else 1024
        a = torch.randn(n, n, device=device)
        sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
        a @ a  # warm-up: thread pool, cuBLAS handle
        best = float("inf")
        for _ in range(6):  # the fastest: the least disturbed by other processes
            sync()
            start = time.perf_counter()
            a @ a
            sync()
            best = min(best, time.perf_counter() - start)
        _MATMUL_RATES[str(device)] = 2 * n**3 / best
    return _MATMUL_RATES[str(device)]


def check_inference_time(model: Callable, windows: int, vertices: tuple[int, int], device: str | torch.device,
                         force: bool = False) -> float | None:
    """The estimated seconds of `windows` forward windows of `vertices` = (driving, target) vertices:
    warns above `WARN_SECONDS`, `UserError` above `REFUSE_SECONDS` unless `force`. None when not
    checked: a model without `forward_flops` (`model` may be a functools.partial of one), or under
    `MIN_CHECKED_FLOPS` in all."""
    flops_of = getattr(getattr(model, "func", model), "forward_flops", None)
    if flops_of is None:
        return None
    flops = windows * flops_of(*vertices)
    if flops < MIN_CHECKED_FLOPS:
        return None
    rate = matmul_flops_per_second(device)
    seconds = flops / rate
    if seconds > WARN_SECONDS:
        estimate = (f"{windows:,} windows of {vertices[0]:,} driving and {vertices[1]:,} target vertices: at least "
                    f"~{seconds / 60:,.0f} min on {device} ({flops / 1e12:,.1f} TFLOP at the measured "
                    f"{rate / 1e9:,.0f} GFLOP/s; time grows with the square of the vertex count)")
        if seconds > REFUSE_SECONDS and not force:
            raise UserError(f"{estimate}; {DECIMATE_HINT}, or pass --force to run it anyway")
        print(f"warning: {estimate}; to be faster, {DECIMATE_HINT}", file=sys.stderr)
    return seconds


# --------------------------------------------------------------------------------------------
# Driving sequences from files
# --------------------------------------------------------------------------------------------


def driving_files(source: str | os.PathLike) -> list[Path]:
    """The frame files of a driving sequence: a directory's mesh files, or a glob; natural order."""
    path = Path(os.path.expanduser(str(source)))
    if path.is_dir():
        files = [p for p in path.iterdir() if p.suffix.lower() in MESH_SUFFIXES and not p.name.startswith(".")]
        if not files:
            raise MeshError(f"{path}: directory holds no mesh files ({', '.join(MESH_SUFFIXES)})")
    else:
        files = [Path(p) for p in glob.glob(str(path))]
        if not files:
            raise MeshError(f"{source}: no such directory, and no file matches it as a glob")
    return sorted(files, key=lambda p: natural_key(p.name))


def driving_clip(files: list[Path], fps: float | None = None, animation: str | None = None) -> GltfClip | None:
    """The ``animation`` (name or index, default the first) a one-file driving sequence holds (an animated glTF,
    sampled at ``fps``: `aniformer.io.gltf_scene`), else None: the files are the frames. An animated glTF among
    other frames is refused (its animation would be dropped for its rest pose), and so is ``animation`` where
    there is no one file to play it from."""
    if len(files) == 1:
        clip = gltf_clip(files[0], fps, animation)
        if clip is None and animation is not None:
            raise MeshError(f"{files[0]}: --animation {animation!r}, but the file holds no animation")
        return clip
    if animation is not None:
        raise MeshError(f"--animation {animation!r} plays an animation of one glTF --driving file, not of "
                        f"{len(files):,} frame files")
    for path in files:
        if gltf_clip(path) is not None:
            raise MeshError(f"{path}: an animated glTF among {len(files):,} driving files; pass it alone as "
                            "--driving to play its animation")
    return None


def driving_unit(files: list[Path], clip: GltfClip | None, max_vertices: int, unit: str) -> tuple[str, str]:
    """(unit, why) of a driving sequence, from its first frame (`aniformer.io.mesh.load_body_mesh`)."""
    if clip is None:
        return load_body_mesh(files[0], max_vertices, unit)[2]
    vertices, _ = clip.sample(1)
    return body_unit(vertices[0], files[0], unit)


def load_driving(files: list[Path], max_vertices: int = DEFAULT_MAX_VERTICES, unit: str = "m",
                 progress: Callable[[int], None] | None = None,
                 clip: GltfClip | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Load frames -> (vertices (N, V, 3) float32 metres, faces); every frame must have the first one's faces.
    With ``clip`` (`driving_clip`), its frames instead of the files'."""
    if clip is not None:
        vertices, faces = clip.sample()
        vertices = vertices * UNITS[unit]
        for k, frame in enumerate(vertices):
            validate_mesh(frame, faces, f"{files[0]} at {k / clip.fps:.3f} s", max_vertices)
        if progress is not None:
            progress(len(vertices))
        return vertices.astype(np.float32), faces
    frames, faces = [], None
    for path in files:
        vertices, f = load_mesh(path, max_vertices=max_vertices, unit=unit)
        if faces is None:
            faces = f
        elif len(vertices) != len(frames[0]):
            raise MeshError(f"{path}: {len(vertices):,} vertices, but the first driving frame {files[0].name} "
                            f"has {len(frames[0]):,} (all frames of a sequence must share one mesh)")
        elif not np.array_equal(f, faces):
            raise MeshError(f"{path}: other faces than the first driving frame {files[0].name} "
                            "(all frames of a sequence must share one mesh)")
        frames.append(vertices)
        if progress is not None:
            progress(1)
    if not frames:
        raise MeshError("the driving sequence has no frames")
    return np.stack(frames), faces


FPS_SIDECARS = ("sequence.json", "export.json")  # beside the frames: {"fps": 60, ...}


def driving_frames(files: list[Path], clip: GltfClip | None) -> int:
    """How many frames a driving sequence has: its glTF animation's as sampled (``clip``), else one per file."""
    return clip.frames if clip is not None else len(files)


def driving_fps(files: list[Path], clip: GltfClip | None = None) -> float | None:
    """The frame rate of a driving sequence: its glTF animation's as sampled (``clip``), else the one a JSON file
    beside the frames declares (``FPS_SIDECARS``), else None."""
    if clip is not None:
        return clip.fps
    for sidecar in (files[0].parent / name for name in FPS_SIDECARS):
        if not sidecar.is_file():
            continue
        try:
            fps = json.loads(sidecar.read_text()).get("fps")
        except (OSError, ValueError, AttributeError) as e:
            raise MeshError(f"{sidecar}: not a readable JSON object ({type(e).__name__})") from None
        if fps is None:
            continue
        if isinstance(fps, bool) or not isinstance(fps, int | float) or not 0 < fps < float("inf"):
            raise MeshError(f"{sidecar}: fps must be a positive number, got {fps!r}")
        return float(fps)
    return None


# --------------------------------------------------------------------------------------------
# Sliding-window inference
# --------------------------------------------------------------------------------------------


def window_plan(frames: int, window: int, outputs: slice, combine: str = "mean") -> tuple[int, int, list[int]]:
    """(front padding, back padding, predicted offsets used) for a sequence of ``frames`` frames.

    ``outputs`` is the model's ``config.output_frames()``; windows start at every frame of the
    padded sequence, and window s's prediction at offset o belongs to frame s + o - front.
    """
    if combine not in COMBINE_RULES:
        raise ValueError(f"combine must be one of {COMBINE_RULES}, got {combine!r}")
    offsets = list(range(window))[outputs]
    centre = window // 2
    if combine == "center" or offsets != list(range(window)):
        if centre not in offsets:
            raise ValueError(f"the model does not predict the centre frame of its window ({offsets})")
        return centre, window - 1 - centre, [centre]
    return 0, max(0, window - frames), offsets


def _center(windows: torch.Tensor, mode: str) -> torch.Tensor:
    if mode == "mesh":
        return center_bbox(windows)
    if mode == "window":  # one offset per window, as pipeline.data does for center="window"
        B, T, V, _ = windows.shape
        return center_bbox(windows.reshape(B, T * V, 3)).reshape(B, T, V, 3)
    return windows


def animate_sequence(
    model: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    driving: np.ndarray | torch.Tensor,
    target: np.ndarray | torch.Tensor,
    *,
    window: int,
    outputs: slice = slice(None),
    combine: str = "mean",
    center: str = "mesh",
    batch_size: int = 8,
    device: str | torch.device = "cpu",
    progress: Callable[[int], None] | None = None,
    force: bool = False,
) -> np.ndarray:
    """Animate ``target (V2, 3)`` with ``driving (N, V1, 3)`` -> ``(N, V2, 3)`` float32 (see module doc).

    ``model(driving (B, T, V1, 3), target (B, V2, 3))`` returns the frames ``outputs`` of each
    window; ``progress(k)`` is called after every batch with the number of windows it held. Before
    the first window the time is estimated (``check_inference_time``): a warning beyond
    ``WARN_SECONDS``, a ``UserError`` beyond ``REFUSE_SECONDS`` unless ``force``.
    """
    if center not in CENTER_MODES:
        raise ValueError(f"center must be one of {CENTER_MODES}, got {center!r}")
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    import torch

    with torch.no_grad():  # not inference_mode: roma caches tensors made here, and autograd (registration) refuses them
        device = torch.device(device)
        raw = torch.as_tensor(np.asarray(driving, np.float32))
        target_t = torch.as_tensor(np.asarray(target, np.float32))
        N, V2 = len(raw), len(target_t)
        front, back, offsets = window_plan(N, window, outputs, combine)
        first_out = list(range(window))[outputs]
        columns = [first_out.index(o) for o in offsets]  # where each used offset sits in the model output
        index = torch.cat([torch.zeros(front, dtype=torch.long), torch.arange(N),
                           torch.full((back,), N - 1, dtype=torch.long)])
        starts = torch.arange(len(index) - window + 1)
        check_inference_time(model, len(starts), (raw.shape[1], V2), device, force)
        drv = raw if center == "window" else _center(raw.unsqueeze(0), center)[0]
        tgt = (center_bbox(target_t) if center != "none" else target_t).to(device)
        total = torch.zeros(N, V2, 3, dtype=torch.float64)
        count = torch.zeros(N, dtype=torch.float64)
        steps = torch.arange(window)
        for lo in range(0, len(starts), batch_size):
            s = starts[lo:lo + batch_size]
            windows = drv[index[s[:, None] + steps]]  # (B, T, V1, 3)
            if center == "window":
                windows = _center(windows, "window")
            pred = model(windows.to(device), tgt.expand(len(s), V2, 3)).float().cpu()
            for column, offset in zip(columns, offsets):
                frame = s + offset - front
                keep = (frame >= 0) & (frame < N)
                total.index_add_(0, frame[keep], pred[keep, column].double())
                count.index_add_(0, frame[keep], torch.ones(int(keep.sum()), dtype=torch.float64))
            if progress is not None:
                progress(len(s))
        assert bool((count > 0).all()), "every frame is covered by a window"
        return (total / count[:, None, None]).float().numpy()


def body_scale(target: np.ndarray, target_faces: np.ndarray, driver: np.ndarray, driver_faces: np.ndarray) -> float:
    """The size of a target body ``(V2, 3)`` over a driver's ``(V1, 3)``: the square root of their surface
    areas' ratio, the same in any pose and orientation and for any topology (heights are not: a kneeling body)."""
    import trimesh

    areas = [trimesh.triangles.area(np.asarray(v, np.float64)[f]).sum() for v, f in ((target, target_faces),
                                                                                  (driver, driver_faces))]
    return float(np.sqrt(areas[0] / areas[1])) if areas[1] > 0 else 1.0


def root_motion(driving: np.ndarray, local: np.ndarray, scale: float) -> np.ndarray:
    """(N, 3) translations that put bbox-centred output frames ``local (N, V2, 3)`` where the driver is (z up).

    Horizontally the result starts at the driver's first bbox centre and travels the driver's
    path scaled by ``scale`` (the target's size over the driver's, ``body_scale``), so a smaller body
    takes smaller steps. Vertically the driver's lowest point over the clip is the floor, and the
    floor goes to z = 0 (where clients draw the ground): the result's lowest point stands on it
    whenever the driver's does, and rises ``scale`` times as high.
    """
    centres = (driving.min(1) + driving.max(1)) / 2
    lowest = driving[..., 2].min(1)
    floor = lowest.min()
    xy = centres[0, :2] + scale * (centres[:, :2] - centres[0, :2])
    z = scale * (lowest - floor) - local[..., 2].min(1)
    return np.concatenate([xy, z[:, None]], 1).astype(np.float32)


def num_windows(frames: int, window: int, outputs: slice = slice(None), combine: str = "mean") -> int:
    front, back, _ = window_plan(frames, window, outputs, combine)
    return frames + front + back - window + 1
