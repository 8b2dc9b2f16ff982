"""Animate a target mesh with a driving sequence of any length, and write the result as glTF.

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

Centring: every driving frame and the target are bounding-box centred like the training pairs
(``center="mesh"``; ``"window"`` centres each window as a whole, ``"none"`` not at all: use the
checkpoint's ``data.center``). The model outputs centred meshes, so the result is centred frame by
frame: a hop stays in place. ``trajectory=True`` re-adds the driver's bounding-box-centre path
(relative to its first frame, scaled by target height / driver height, z up).

glTF
----
``write_glb`` writes a binary glTF 2.0 file by hand (trimesh can neither write nor read morph
targets): one mesh whose base POSITION is the first frame, one morph target per frame (POSITION
deltas from the base; frame 0's is zero), and one animation whose ``weights`` channel switches
the active morph target with STEP interpolation at ``fps``. See docs/animate.md for the layout.
"""

from __future__ import annotations

import glob
import json
import os
import re
import struct
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from aniformer.cli import atomic_path
from aniformer.mesh import DEFAULT_MAX_VERTICES, MESH_SUFFIXES, MeshError, center_bbox, load_mesh

COMBINE_RULES = ("mean", "center")
CENTER_MODES = ("mesh", "window", "none")


# --------------------------------------------------------------------------------------------
# Driving sequences from files
# --------------------------------------------------------------------------------------------


def natural_key(name: str) -> list:
    """Sort key that orders frame_2 before frame_10."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


def driving_files(spec: str | os.PathLike) -> list[Path]:
    """The frame files of a driving sequence: a directory's mesh files, or a glob; natural order."""
    path = Path(os.path.expanduser(str(spec)))
    if path.is_dir():
        files = [p for p in path.iterdir() if p.suffix.lower() in MESH_SUFFIXES and not p.name.startswith(".")]
        if not files:
            raise MeshError(f"{path}: directory holds no mesh files ({', '.join(MESH_SUFFIXES)})")
    else:
        files = [Path(p) for p in glob.glob(str(path))]
        if not files:
            raise MeshError(f"{spec}: no such directory, and no file matches it as a glob")
    return sorted(files, key=lambda p: natural_key(p.name))


def load_driving(files: list[Path], max_vertices: int = DEFAULT_MAX_VERTICES,
                 progress: Callable[[int], None] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Load frames -> (vertices (N, V, 3) float32, faces of the first frame); all must share V."""
    frames, faces = [], None
    for path in files:
        vertices, f = load_mesh(path, max_vertices=max_vertices)
        if faces is None:
            faces = f
        elif len(vertices) != len(frames[0]):
            raise MeshError(f"{path}: {len(vertices):,} vertices, but the first driving frame {files[0].name} "
                            f"has {len(frames[0]):,} (all frames of a sequence must share one mesh)")
        frames.append(vertices)
        if progress is not None:
            progress(1)
    if not frames:
        raise MeshError("the driving sequence has no frames")
    return np.stack(frames), faces


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


@torch.inference_mode()
def animate_sequence(
    model: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    driving: np.ndarray | torch.Tensor,
    target: np.ndarray | torch.Tensor,
    *,
    window: int,
    outputs: slice = slice(None),
    combine: str = "mean",
    center: str = "mesh",
    trajectory: bool = False,
    batch_size: int = 8,
    device: str | torch.device = "cpu",
    progress: Callable[[int], None] | None = None,
) -> np.ndarray:
    """Animate ``target (V2, 3)`` with ``driving (N, V1, 3)`` -> ``(N, V2, 3)`` float32 (see module doc).

    ``model(driving (B, T, V1, 3), target (B, V2, 3))`` returns the frames ``outputs`` of each
    window; ``progress(k)`` is called after every batch with the number of windows it held.
    """
    if center not in CENTER_MODES:
        raise ValueError(f"center must be one of {CENTER_MODES}, got {center!r}")
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
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
    result = (total / count[:, None, None]).float().numpy()
    if trajectory:
        result = result + driver_trajectory(raw.numpy(), target_t.numpy())[:, None, :]
    return result


def driver_trajectory(driving: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(N, 3): the driver's bbox-centre path relative to frame 0, scaled by target / driver height (z)."""
    centres = (driving.min(1) + driving.max(1)) / 2
    driver_height = float(np.ptp(driving[0, :, 2]))
    scale = float(np.ptp(target[:, 2])) / driver_height if driver_height > 0 else 1.0
    return ((centres - centres[0]) * scale).astype(np.float32)


def num_windows(frames: int, window: int, outputs: slice = slice(None), combine: str = "mean") -> int:
    front, back, _ = window_plan(frames, window, outputs, combine)
    return frames + front + back - window + 1


# --------------------------------------------------------------------------------------------
# Binary glTF 2.0 with one morph target per frame
# --------------------------------------------------------------------------------------------

_FLOAT, _UINT = 5126, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_GLB_MAGIC, _JSON_CHUNK, _BIN_CHUNK = 0x46546C67, 0x4E4F534A, 0x004E4942


def _public(path: Path) -> None:
    """mkstemp makes files 0600; outputs are ordinary files (0666 minus the umask)."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(path, 0o666 & ~umask)


def write_glb(path: str | os.PathLike, frames: np.ndarray, faces: np.ndarray, fps: float = 30.0,
              name: str = "aniformer", extras: dict | None = None) -> Path:
    """Write ``frames (N, V, 3)`` sharing ``faces (F, 3)`` as an animated GLB (atomically).

    Base POSITION = frame 0; morph target k = frame k - frame 0; animation "``name``" sets weight k
    to 1 (all others 0) from time k / fps, STEP interpolation. Scene extras hold ``frames``/``fps``.
    """
    frames = np.ascontiguousarray(frames, np.float32)
    faces = np.ascontiguousarray(faces, np.uint32)
    if frames.ndim != 3 or frames.shape[2] != 3 or len(frames) == 0:
        raise ValueError(f"frames must have shape (N, V, 3) with N >= 1, got {frames.shape}")
    if not np.isfinite(frames).all():
        raise ValueError("frames contain NaN or infinity")
    if fps <= 0:
        raise ValueError(f"fps must be positive, got {fps}")
    N, V, _ = frames.shape
    base = frames[0]
    deltas = frames - base
    times = (np.arange(N) / fps).astype(np.float32)
    weights = np.eye(N, dtype=np.float32)  # key k: weight k = 1

    blobs: list[bytes] = []
    views: list[dict] = []
    offset = 0

    def add_view(data: bytes, target: int | None) -> int:
        nonlocal offset
        view = {"buffer": 0, "byteOffset": offset, "byteLength": len(data)}
        if target is not None:
            view["target"] = target
        pad = (-len(data)) % 4
        blobs.append(data + b"\0" * pad)
        offset += len(data) + pad
        views.append(view)
        return len(views) - 1

    accessors: list[dict] = []

    def add_accessor(view: int, kind: str, count: int, component: int, byte_offset: int = 0,
                     low=None, high=None) -> int:
        accessor = {"bufferView": view, "byteOffset": byte_offset, "componentType": component,
                    "count": int(count), "type": kind}
        if low is not None:
            accessor["min"], accessor["max"] = [float(x) for x in np.atleast_1d(low)], [float(x) for x in np.atleast_1d(high)]
        accessors.append(accessor)
        return len(accessors) - 1

    indices = add_accessor(add_view(faces.tobytes(), _ELEMENT_ARRAY_BUFFER), "SCALAR", faces.size, _UINT,
                           low=int(faces.min()), high=int(faces.max()))
    position = add_accessor(add_view(base.tobytes(), _ARRAY_BUFFER), "VEC3", V, _FLOAT,
                            low=base.min(0), high=base.max(0))
    delta_view = add_view(deltas.tobytes(), _ARRAY_BUFFER)
    targets = [
        {"POSITION": add_accessor(delta_view, "VEC3", V, _FLOAT, k * V * 12, deltas[k].min(0), deltas[k].max(0))}
        for k in range(N)
    ]
    time_acc = add_accessor(add_view(times.tobytes(), None), "SCALAR", N, _FLOAT, low=times[0], high=times[-1])
    weight_acc = add_accessor(add_view(weights.tobytes(), None), "SCALAR", N * N, _FLOAT)
    digits = max(4, len(str(N - 1)))
    gltf = {
        "asset": {"version": "2.0", "generator": "aniformer.animate"},
        "scene": 0,
        "scenes": [{"nodes": [0], "extras": {"frames": N, "fps": float(fps), **(extras or {})}}],
        "nodes": [{"mesh": 0, "name": name}],
        "meshes": [{
            "name": name,
            "primitives": [{"attributes": {"POSITION": position}, "indices": indices, "targets": targets,
                            "mode": 4, "material": 0}],
            "weights": [0.0] * N,
            "extras": {"targetNames": [f"frame_{k:0{digits}d}" for k in range(N)]},
        }],
        "materials": [{"name": "body", "doubleSided": True,
                       "pbrMetallicRoughness": {"baseColorFactor": [0.62, 0.70, 0.86, 1.0],
                                                "metallicFactor": 0.0, "roughnessFactor": 0.8}}],
        "animations": [{"name": name,
                        "samplers": [{"input": time_acc, "output": weight_acc, "interpolation": "STEP"}],
                        "channels": [{"sampler": 0, "target": {"node": 0, "path": "weights"}}]}],
        "buffers": [{"byteLength": offset}],
        "bufferViews": views,
        "accessors": accessors,
    }
    text = json.dumps(gltf, separators=(",", ":")).encode()
    text += b" " * ((-len(text)) % 4)
    binary = b"".join(blobs)
    total = 12 + 8 + len(text) + 8 + len(binary)
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(struct.pack("<III", _GLB_MAGIC, 2, total))
        f.write(struct.pack("<II", len(text), _JSON_CHUNK) + text)
        f.write(struct.pack("<II", len(binary), _BIN_CHUNK) + binary)
        _public(tmp)
    return path


def read_glb(path: str | os.PathLike) -> dict:
    """Read back a GLB written by ``write_glb``: {"frames" (N, V, 3), "faces", "times", "weights", "gltf"}."""
    data = Path(path).read_bytes()
    magic, version, length = struct.unpack_from("<III", data, 0)
    if magic != _GLB_MAGIC or version != 2 or length != len(data):
        raise ValueError(f"{path}: not a binary glTF 2.0 file")
    json_len, json_type = struct.unpack_from("<II", data, 12)
    gltf = json.loads(data[20:20 + json_len])
    bin_start = 20 + json_len + 8
    binary = data[bin_start:bin_start + struct.unpack_from("<I", data, 20 + json_len)[0]]
    sizes = {"SCALAR": 1, "VEC3": 3}
    dtypes = {_FLOAT: np.float32, _UINT: np.uint32}

    def accessor(i: int) -> np.ndarray:
        a = gltf["accessors"][i]
        view = gltf["bufferViews"][a["bufferView"]]
        start = view.get("byteOffset", 0) + a.get("byteOffset", 0)
        n = a["count"] * sizes[a["type"]]
        arr = np.frombuffer(binary, dtypes[a["componentType"]], n, start)
        return arr.reshape(a["count"], sizes[a["type"]]) if a["type"] != "SCALAR" else arr

    primitive = gltf["meshes"][0]["primitives"][0]
    base = accessor(primitive["attributes"]["POSITION"])
    deltas = np.stack([accessor(t["POSITION"]) for t in primitive["targets"]])
    sampler = gltf["animations"][0]["samplers"][0]
    times = accessor(sampler["input"])
    weights = accessor(sampler["output"]).reshape(len(times), -1)
    active = weights.argmax(1)  # the morph target switched on at each key
    return {"frames": base + deltas[active], "faces": accessor(primitive["indices"]).reshape(-1, 3).astype(np.int64),
            "times": times, "weights": weights, "gltf": gltf}


def write_obj(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray) -> Path:
    """A plain OBJ (v / f lines, 1-based), written atomically; faster than trimesh's exporter."""
    lines = ["# aniformer"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in np.asarray(vertices, np.float64)]
    lines += [f"f {a} {b} {c}" for a, b, c in np.asarray(faces, np.int64) + 1]
    with atomic_path(path) as tmp:
        Path(tmp).write_text("\n".join(lines) + "\n")
        _public(tmp)
    return Path(path)
