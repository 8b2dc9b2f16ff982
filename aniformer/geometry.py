"""Array geometry with no file formats: the project's axes (z up) against a file's, bounding-box centring and
vertex reordering; numpy (``center_bbox`` also torch). The model core uses it; ``aniformer.io.mesh`` reads and
writes the files."""

from __future__ import annotations

import numpy as np

UP_AXES = ("z", "y")  # the axis a file's bodies stand along: z (Anny, Blender's scene) or y (glTF, OBJ exports)
STANDS_ALONG = "the body stands along {}"  # why `detect_up` chose an axis: the body, not --up or the format
# vertex-frames per step of the per-frame work over a whole clip (carry-back, stretch): its temporaries stay in the
# cache; 300 frames of 72k vertices carried back in 5.4 s at 262k per step, 9.8 s at 32 frames (2.3M)
CHUNK_VERTEX_FRAMES = 2**18


def frames_per_chunk(vertices: int) -> int:
    """How many frames of a ``vertices``-vertex mesh to take at a time (``CHUNK_VERTEX_FRAMES``)."""
    return max(1, CHUNK_VERTEX_FRAMES // max(1, vertices))


def to_z_up(vertices: np.ndarray, up: str) -> np.ndarray:
    """Vertices ``(..., 3)`` of a file whose up axis is ``up`` in the project's z-up axes (glTF's y-up
    (x, y, z) is (x, -z, y) here: the inverse of what ``aniformer.io.glb`` writes)."""
    if up == "z":
        return vertices
    x, y, z = np.moveaxis(np.asarray(vertices), -1, 0)
    return np.stack([x, -z, y], -1)


def from_z_up(vertices: np.ndarray, up: str) -> np.ndarray:
    """Vertices ``(..., 3)`` in z-up axes back in a file's axes whose up axis is ``up`` (inverse of ``to_z_up``)."""
    if up == "z":
        return vertices
    x, y, z = np.moveaxis(np.asarray(vertices), -1, 0)
    return np.stack([x, z, -y], -1)


# How meshes are centred for the model: each on its own bounding box (the paper), each window's frames on
# their joint box, or not at all.
CENTER_MODES = ("mesh", "window", "none")


def center_bbox(vertices):
    """Centre meshes on their bounding box, as the paper does; works on numpy or torch `(..., V, 3)`."""
    if isinstance(vertices, np.ndarray):
        low, high = vertices.min(-2, keepdims=True), vertices.max(-2, keepdims=True)
    else:
        low, high = vertices.amin(-2, keepdim=True), vertices.amax(-2, keepdim=True)
    return vertices - (low + high) / 2


def shuffle_vertices(vertices: np.ndarray, faces: np.ndarray, perm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reorder vertices `(..., V, 3)` by `perm` (new i = old perm[i]) and remap faces so triangles stay the same."""
    inverse = np.empty_like(perm)
    inverse[perm] = np.arange(len(perm))
    return vertices[..., perm, :], inverse[faces]
