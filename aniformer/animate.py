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

Huge meshes: attention is linear in memory but quadratic in time with the vertex count. Before the
first window, ``animate_sequence`` estimates the inference time from the model's FLOP count
(``forward_flops``) and a matrix product timed on the device (``matmul_flops_per_second``). Above
``WARN_SECONDS`` it warns on stderr, above ``REFUSE_SECONDS`` it refuses unless ``force``; both
give the estimate and point to decimating the target first.

Centring: every driving frame and the target are bounding-box centred like the training pairs
(``center="mesh"``; ``"window"`` centres each window as a whole, ``"none"`` not at all: use the
checkpoint's ``data.center``). The model outputs centred meshes; ``root_motion`` gives the
translation that puts each output frame where the driver is (world space).

glTF
----
``write_glb`` writes a binary glTF 2.0 file by hand (trimesh can neither write nor read morph
targets): y up, the clip split into meshes of at most ``FRAMES_PER_MESH`` frames, each a base
POSITION plus one morph target per later frame switched by sparse one-hot weights, the chunk on
show picked by its node's scale, and the root motion on the root node; STEP keys at k / fps and
an end key at N / fps. See docs/animate.md for the layout.
"""

from __future__ import annotations

import glob
import json
import os
import struct
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from aniformer.errors import MeshError, UserError
from aniformer.files import atomic_path, natural_key
from aniformer.mesh import DEFAULT_MAX_VERTICES, MESH_SUFFIXES, center_bbox, load_mesh

COMBINE_RULES = ("mean", "center")
CENTER_MODES = ("mesh", "window", "none")
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


def load_driving(files: list[Path], max_vertices: int = DEFAULT_MAX_VERTICES, unit: str = "m",
                 progress: Callable[[int], None] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Load frames -> (vertices (N, V, 3) float32 metres, faces); every frame must have the first one's faces."""
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


def driving_fps(files: list[Path]) -> float | None:
    """The frame rate a JSON file beside the driving frames declares (``FPS_SIDECARS``), else None."""
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


@torch.no_grad()  # not inference_mode: roma caches tensors made here, and autograd (registration) refuses them
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


def root_motion(driving: np.ndarray, local: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(N, 3) translations that put bbox-centred output frames ``local (N, V2, 3)`` where the driver is (z up).

    Horizontally the result starts at the driver's first bbox centre and travels the driver's
    path scaled by s = target height / driver height (z extents of the target and the first
    driving frame), so a smaller body takes smaller steps. Vertically the driver's lowest point
    over the clip is the floor, and the floor goes to z = 0 (where clients draw the ground): the
    result's lowest point stands on it whenever the driver's does, and rises s times as high.
    """
    centres = (driving.min(1) + driving.max(1)) / 2
    lowest = driving[..., 2].min(1)
    floor = lowest.min()
    driver_height = float(np.ptp(driving[0, :, 2]))
    scale = float(np.ptp(target[:, 2])) / driver_height if driver_height > 0 else 1.0
    xy = centres[0, :2] + scale * (centres[:, :2] - centres[0, :2])
    z = scale * (lowest - floor) - local[..., 2].min(1)
    return np.concatenate([xy, z[:, None]], 1).astype(np.float32)


def num_windows(frames: int, window: int, outputs: slice = slice(None), combine: str = "mean") -> int:
    front, back, _ = window_plan(frames, window, outputs, combine)
    return frames + front + back - window + 1


# --------------------------------------------------------------------------------------------
# Binary glTF 2.0: morph-target meshes in chunks, root motion on the node
# --------------------------------------------------------------------------------------------

_FLOAT, _UINT = 5126, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_GLB_MAGIC, _JSON_CHUNK, _BIN_CHUNK = 0x46546C67, 0x4E4F534A, 0x004E4942
FRAMES_PER_MESH = 256  # frames per mesh by default: WebGL2 guarantees 256 texture-array layers
MAX_MORPH_TARGETS = 2048  # three.js keeps a mesh's morph targets in one texture array; beyond this it freezes
MAX_GLB_BYTES = 2**31 - 1  # browsers (three.js) load a GLB into one ArrayBuffer; the GLB header counts in uint32


def to_gltf_axes(vertices: np.ndarray) -> np.ndarray:
    """z-up (the project's convention) -> glTF's y-up: (x, y, z) -> (x, z, -y)."""
    return np.stack([vertices[..., 0], vertices[..., 2], -vertices[..., 1]], -1)


def from_gltf_axes(vertices: np.ndarray) -> np.ndarray:
    """glTF's y-up -> z-up: (x, y, z) -> (x, -z, y); the inverse of ``to_gltf_axes``."""
    return np.stack([vertices[..., 0], -vertices[..., 2], vertices[..., 1]], -1)


def mesh_chunks(frames: int, frames_per_mesh: int = FRAMES_PER_MESH) -> list[tuple[int, int]]:
    """[start, end) frame ranges of the meshes a clip is split into."""
    return [(s, min(s + frames_per_mesh, frames)) for s in range(0, frames, frames_per_mesh)]


def glb_size(frames: int, vertices: int, triangles: int, frames_per_mesh: int = FRAMES_PER_MESH) -> int:
    """Binary size of ``write_glb``'s file, without its JSON (a few hundred bytes per frame)."""
    positions = 12 * vertices * (frames + len(mesh_chunks(frames, frames_per_mesh)))
    return positions + 12 * triangles + 32 * frames  # + keys, sparse weights, translations


class _Buffer:
    """The GLB's binary chunk and the bufferViews / accessors that point into it."""

    def __init__(self):
        self.blobs: list[bytes] = []
        self.views: list[dict] = []
        self.accessors: list[dict] = []
        self.length = 0

    def view(self, data: np.ndarray, target: int | None = None, stride: int | None = None) -> int:
        view = {"buffer": 0, "byteOffset": self.length, "byteLength": data.nbytes}
        view.update({"target": target} if target else {})
        view.update({"byteStride": stride} if stride else {})
        blob = np.ascontiguousarray(data).tobytes()
        self.blobs.append(blob + b"\0" * (-len(blob) % 4))
        self.length += len(self.blobs[-1])
        self.views.append(view)
        return len(self.views) - 1

    def accessor(self, view: int | None, kind: str, count: int, component: int = _FLOAT, offset: int = 0,
                 bounds: np.ndarray | None = None, **extra) -> int:
        accessor = {"componentType": component, "count": int(count), "type": kind, **extra}
        if view is not None:
            accessor.update(bufferView=view, byteOffset=offset)
        if bounds is not None:  # required on POSITION and animation inputs
            accessor["min"] = np.atleast_2d(bounds).min(0).astype(float).tolist()
            accessor["max"] = np.atleast_2d(bounds).max(0).astype(float).tolist()
        self.accessors.append(accessor)
        return len(self.accessors) - 1

    def array(self, values: np.ndarray, kind: str, bounds: bool = False) -> int:
        """An accessor over a fresh view of float32 ``values`` (animation data)."""
        values = np.asarray(values, np.float32)
        return self.accessor(self.view(values), kind, len(values), bounds=values.reshape(len(values), -1) if bounds else None)

    def sparse_one_hot(self, keys: int, targets: int) -> int:
        """(keys x targets) weights where key j + 1 sets target j to 1 and key 0 none (frame = base):
        stored sparse, so linear in the frames, not quadratic."""
        hot = np.arange(1, keys, dtype=np.uint32)
        index = hot * targets + np.minimum(hot, targets) - 1  # the end key repeats the last frame
        sparse = {"count": len(index),
                  "indices": {"bufferView": self.view(index), "componentType": _UINT},
                  "values": {"bufferView": self.view(np.ones(len(index), np.float32))}}
        return self.accessor(None, "SCALAR", keys * targets, sparse=sparse)


def _mesh_and_weights(buf: _Buffer, frames: np.ndarray, indices: int, name: str) -> tuple[dict, int | None]:
    """A mesh whose base is ``frames[0]`` with one morph target per later frame, and its weights output."""
    base, deltas = frames[0], frames[1:] - frames[0]
    position = buf.accessor(buf.view(base, _ARRAY_BUFFER), "VEC3", len(base), bounds=base)
    primitive = {"attributes": {"POSITION": position}, "indices": indices, "mode": 4, "material": 0}
    mesh = {"name": name, "primitives": [primitive]}
    if not len(deltas):
        return mesh, None
    view = buf.view(deltas, _ARRAY_BUFFER, stride=12)  # several accessors in one view need byteStride
    V = len(base)
    primitive["targets"] = [{"POSITION": buf.accessor(view, "VEC3", V, offset=k * V * 12, bounds=d)}
                            for k, d in enumerate(deltas)]
    mesh["weights"] = [0.0] * len(deltas)
    mesh["extras"] = {"targetNames": [f"frame_{k}" for k in range(1, len(frames))]}
    return mesh, buf.sparse_one_hot(len(frames) + 1, len(deltas))


def _visibility(start: int, end: int, frames: int) -> tuple[list[int], list[float]]:
    """STEP keys (frame numbers) and scales that show a chunk for frames [start, end) only."""
    keys, scales = [0], [1.0 if start == 0 else 0.0]
    if start > 0:
        keys, scales = keys + [start], scales + [1.0]
    if end < frames:
        keys, scales = keys + [end], scales + [0.0]
    return keys + [frames], scales + [scales[-1]]


def write_glb(path: str | os.PathLike, frames: np.ndarray, faces: np.ndarray, fps: float = 30.0,
              name: str = "aniformer", translation: np.ndarray | None = None,
              frames_per_mesh: int = FRAMES_PER_MESH, extras: dict | None = None) -> Path:
    """Write ``frames (N, V, 3)`` (z up, metres) sharing ``faces (F, 3)`` as an animated GLB, atomically.

    glTF is y up: positions are written as (x, z, -y). The clip is split into meshes of at most
    ``frames_per_mesh`` frames (child nodes of one root node ``name``); each has its first frame as
    base and one morph target per later frame, switched by sparse one-hot weights. Only the
    current chunk has scale 1. ``translation (N, 3)`` (z up), if given, animates the root node
    (root motion). Every channel is STEP with keys k / fps and one end key at N / fps, so the clip
    lasts N / fps. See docs/animate.md for the layout.
    """
    frames = np.asarray(frames, np.float32)
    if frames.ndim != 3 or frames.shape[2] != 3 or len(frames) == 0:
        raise ValueError(f"frames must have shape (N, V, 3) with N >= 1, got {frames.shape}")
    if not np.isfinite(frames).all():
        raise ValueError("frames contain NaN or infinity")
    if not 0 < fps < float("inf"):
        raise ValueError(f"fps must be positive, got {fps}")
    frames = to_gltf_axes(frames)
    faces = np.ascontiguousarray(faces, np.uint32)
    N = len(frames)
    buf = _Buffer()
    indices = buf.accessor(buf.view(faces.ravel(), _ELEMENT_ARRAY_BUFFER), "SCALAR", faces.size, _UINT,
                           bounds=faces.reshape(-1, 1))
    all_times = (np.arange(N + 1) / fps).astype(np.float32)
    time_view = buf.view(all_times) if N > 1 else None  # a single frame has no animation
    chunks = mesh_chunks(N, frames_per_mesh)
    several = len(chunks) > 1
    nodes = [{"name": name, "children": list(range(1, len(chunks) + 1))}]
    meshes, samplers, channels = [], [], []

    def animate(node: int, path: str, keys: list[int] | np.ndarray, output: int) -> None:
        keys = np.asarray(keys)
        if np.array_equal(keys, np.arange(keys[0], keys[-1] + 1)):  # a slice of the shared key times
            times = buf.accessor(time_view, "SCALAR", len(keys), offset=4 * int(keys[0]), bounds=all_times[keys, None])
        else:
            times = buf.array(all_times[keys], "SCALAR", bounds=True)
        samplers.append({"input": times, "output": output, "interpolation": "STEP"})
        channels.append({"sampler": len(samplers) - 1, "target": {"node": node, "path": path}})

    for c, (start, end) in enumerate(chunks):
        label = f"{name}_{start:0{len(str(N))}d}" if several else name
        mesh, weights = _mesh_and_weights(buf, frames[start:end], indices, label)
        nodes.append({"name": label, "mesh": c, **({"scale": [0.0] * 3} if start > 0 else {})})
        meshes.append(mesh)
        if weights is not None:
            animate(c + 1, "weights", np.arange(start, end + 1), weights)
        if several:
            keys, scales = _visibility(start, end, N)
            animate(c + 1, "scale", keys, buf.array(np.repeat(np.array(scales)[:, None], 3, 1), "VEC3"))
    if translation is not None:
        moves = to_gltf_axes(np.asarray(translation, np.float32))
        nodes[0]["translation"] = moves[0].astype(float).tolist()
        if N > 1:
            animate(0, "translation", np.arange(N + 1), buf.array(np.concatenate([moves, moves[-1:]]), "VEC3"))

    gltf = {
        "asset": {"version": "2.0", "generator": "aniformer.animate"},
        "scene": 0,
        "scenes": [{"name": name, "nodes": [0], "extras": {"frames": N, "fps": float(fps), **(extras or {})}}],
        "nodes": nodes,
        "meshes": meshes,
        "materials": [{"name": "body", "doubleSided": True,
                       "pbrMetallicRoughness": {"baseColorFactor": [0.62, 0.70, 0.86, 1.0],
                                                "metallicFactor": 0.0, "roughnessFactor": 0.8}}],
        "buffers": [{"byteLength": buf.length}],
        "bufferViews": buf.views,
        "accessors": buf.accessors,
    }
    if channels:  # glTF requires at least one channel per animation
        gltf["animations"] = [{"name": name, "samplers": samplers, "channels": channels,
                               "extras": {"fps": float(fps), "frames": N}}]
    return _write_glb_file(Path(path), gltf, b"".join(buf.blobs))


def _write_glb_file(path: Path, gltf: dict, binary: bytes) -> Path:
    text = json.dumps(gltf, separators=(",", ":")).encode()
    text += b" " * ((-len(text)) % 4)
    total = 12 + 8 + len(text) + 8 + len(binary)
    if total > MAX_GLB_BYTES:
        raise ValueError(f"{path.name} would be {total / 2**30:.1f} GiB; glTF clients load at most 2 GiB")
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(struct.pack("<III", _GLB_MAGIC, 2, total))
        f.write(struct.pack("<II", len(text), _JSON_CHUNK) + text)
        f.write(struct.pack("<II", len(binary), _BIN_CHUNK) + binary)
    return path


def read_glb(path: str | os.PathLike) -> dict:
    """Read back a GLB written by ``write_glb``, in the project's axes (z up).

    -> {"frames" (N, V, 3) world positions, "local" (N, V, 3) before the root translation,
    "translation" (N, 3), "faces", "duration" (the last key time of any channel), "gltf"}.
    """
    data = Path(path).read_bytes()
    magic, version, length = struct.unpack_from("<III", data, 0)
    if magic != _GLB_MAGIC or version != 2 or length != len(data):
        raise ValueError(f"{path}: not a binary glTF 2.0 file")
    json_len = struct.unpack_from("<I", data, 12)[0]
    gltf = json.loads(data[20:20 + json_len])
    bin_start = 20 + json_len + 8
    binary = data[bin_start:bin_start + struct.unpack_from("<I", data, 20 + json_len)[0]]
    sizes = {"SCALAR": 1, "VEC3": 3}
    dtypes = {_FLOAT: np.float32, _UINT: np.uint32}

    def accessor(i: int) -> np.ndarray:
        a = gltf["accessors"][i]
        view = gltf["bufferViews"][a["bufferView"]]
        stride = view.get("byteStride", 4 * sizes[a["type"]])  # write_glb's strides are tight
        start = view.get("byteOffset", 0) + a.get("byteOffset", 0)
        arr = np.frombuffer(binary, dtypes[a["componentType"]], a["count"] * stride // 4, start)
        return arr.reshape(a["count"], sizes[a["type"]]) if a["type"] != "SCALAR" else arr

    local = []
    for mesh in gltf["meshes"]:  # chunk meshes in frame order
        primitive = mesh["primitives"][0]
        base = accessor(primitive["attributes"]["POSITION"])
        local += [base] + [base + accessor(t["POSITION"]) for t in primitive.get("targets", [])]
    local = from_gltf_axes(np.stack(local))
    root = gltf["nodes"][0]
    translation = np.broadcast_to(from_gltf_axes(np.array(root.get("translation", [0.0, 0.0, 0.0]), np.float32)),
                                  (len(local), 3))
    duration = 0.0
    for animation in gltf.get("animations", []):
        for channel in animation["channels"]:
            sampler = animation["samplers"][channel["sampler"]]
            if channel["target"] == {"node": 0, "path": "translation"}:
                translation = from_gltf_axes(accessor(sampler["output"])[:-1])
            duration = max(duration, float(accessor(sampler["input"])[-1]))
    faces = accessor(gltf["meshes"][0]["primitives"][0]["indices"]).reshape(-1, 3).astype(np.int64)
    return {"frames": local + translation[:, None], "local": local, "translation": np.asarray(translation),
            "faces": faces, "duration": duration, "gltf": gltf}


def write_obj(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray) -> Path:
    """A plain OBJ (v / f lines, 1-based), written atomically; faster than trimesh's exporter."""
    lines = ["# aniformer"]
    lines += [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in np.asarray(vertices, np.float64)]
    lines += [f"f {a} {b} {c}" for a, b, c in np.asarray(faces, np.int64) + 1]
    with atomic_path(path) as tmp:
        Path(tmp).write_text("\n".join(lines) + "\n")
    return Path(path)
