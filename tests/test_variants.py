"""The target and driver variants of aniformer/synth/variants.py, as built (no registration, no model)."""

from __future__ import annotations

import numpy as np
import trimesh

from aniformer.synth.stream import StreamPairs
from aniformer.synth.variants import DENSE_VERTICES, DRIVER_FRAMES, posed_target_poses, variant_pairs

TOPOLOGY = "notoes_collapse3pc"
NEW_VARIANTS = ["posed", "rotated", "lying", "glb", "seams", "parts", "props", "dense", "foreign_driver"]


class TargetPosesFirst(StreamPairs):
    """Pairs whose driving window starts in the split's target pose, then the ``posed`` target's: the
    ground truth's first two frames are then the target identity as each target variant shows it."""

    def draws(self, split, epoch, indices):
        draws = super().draws(split, epoch, indices)
        draws["motion"][:, 0] = draws["target_pose"]
        draws["motion"][:, 1] = posed_target_poses(self, split, epoch, indices)
        return draws


def _rigid_residual(a: np.ndarray, b: np.ndarray) -> float:
    """The largest distance (m) between ``a`` and ``b (N, 3)`` after the best rotation and translation."""
    a, b = a - a.mean(0), b - b.mean(0)
    u, _, vt = np.linalg.svd(a.T @ b)
    turn = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    return float(np.linalg.norm(a @ turn - b, axis=1).max())


def _long_axis(vertices: np.ndarray) -> np.ndarray:
    return np.linalg.eigh(np.cov((vertices - vertices.mean(0)).T))[1][:, -1]


def test_new_variants_are_foreign_meshes_whose_ground_truth_is_the_target_in_its_own_pose():
    """One pair of every new variant: foreign vertex counts with valid faces, ground truth and copy-driver
    on the target's vertices; where the driving window holds the target's own pose the ground truth
    is the target (through a GLB file, vertices in order), up to a rigid turn for ``rotated`` and
    ``lying``, which lies (its long axis horizontal); ``seams`` is ``posed``'s mesh in 8 islands that touch
    only by position, copies moving as one; ``parts`` adds three separate parts, ``props`` a stick out of the hand
    that keeps its shape in every pose; ``dense``
    passes 50,000 vertices; ``foreign_driver`` drives the model's topology with a longer clip of its own."""
    stream = TargetPosesFirst(TOPOLOGY, window=3, seed=0)
    (pair,) = variant_pairs(stream, "characters", 0, [0], NEW_VARIANTS)
    frame_of_target = {"posed": 1, "rotated": 1, "lying": 0, "glb": 0, "seams": 1, "parts": 0, "props": 0, "dense": 0,
                       "foreign_driver": 0}
    for variant in NEW_VARIANTS:
        case = pair[variant]
        target, faces, truth = case["target"], case["faces"], case["ground_truth"]
        frames = DRIVER_FRAMES if variant == "foreign_driver" else 3
        assert truth.shape == case["copy_driver"].shape == (frames, *target.shape), variant
        assert faces.min() == 0 and faces.max() == len(target) - 1, variant
        assert (len(target) == stream.num_vertices) == (variant == "foreign_driver"), variant
        shown = truth[frame_of_target[variant]]
        if variant in ("rotated", "lying"):
            assert _rigid_residual(shown, target) < 1e-4 and np.abs(shown - target).max() > 0.1, variant
        else:
            np.testing.assert_allclose(shown, target, atol=1e-4, err_msg=variant)
    assert abs(_long_axis(pair["lying"]["target"])[2]) < 0.05 < 0.95 < abs(_long_axis(pair["lying"]["ground_truth"][0])[2])
    posed, parts = pair["posed"], pair["parts"]
    assert len(parts["target"]) == len(posed["target"]) + 2 * 42 + 8  # two icospheres, a box
    on_parts = parts["faces"] >= len(posed["target"])
    assert (on_parts.all(1) | ~on_parts.any(1)).all()  # no face joins a part to the body
    assert len(trimesh.Trimesh(parts["target"], parts["faces"][on_parts.all(1)], process=False).split(only_watertight=False)) == 3
    props = pair["props"]
    stick = props["target"][len(posed["target"]):]
    assert len(stick) == 8 and np.ptp(stick, axis=0).max() > 0.7
    for frames in (props["ground_truth"], props["copy_driver"]):
        assert max(_rigid_residual(frame[len(posed["target"]):], stick) for frame in frames) < 1e-4
    seams = pair["seams"]
    pieces = trimesh.Trimesh(seams["target"], seams["faces"], process=False).split(only_watertight=False)
    assert len(pieces) >= 8  # an island's faces need not all touch
    position, place = np.unique(seams["target"], axis=0, return_inverse=True)
    assert len(seams["target"]) > len(position) == len(posed["target"])  # the same places, some written twice
    for frames in (seams["ground_truth"], seams["copy_driver"]):
        np.testing.assert_array_equal(frames, frames[:, np.unique(place.reshape(-1), return_index=True)[1]][:, place.reshape(-1)])
    assert len(pair["dense"]["target"]) > DENSE_VERTICES
    driver = pair["foreign_driver"]
    assert driver["driving"].shape[0] == DRIVER_FRAMES and driver["driving"].shape[1] != stream.num_vertices
    assert driver["driving_faces"].max() == driver["driving"].shape[1] - 1


def test_a_pair_is_the_same_whatever_is_drawn_with_it():
    """``foreign_driver`` and ``parts`` pair 1 drawn alone and beside pair 0: the same bytes. Made in one batch, Anny's
    bodies differed with the batch at float level (here the targets and ground truth; in an 8-pair batch of the
    shipped model's validation pairs, a driver's decimation came out another mesh, and its fit another basin)."""
    stream = StreamPairs(TOPOLOGY, window=3, seed=0)
    (alone,) = variant_pairs(stream, "seen", 0, [1], ["foreign_driver", "parts"])
    _, beside = variant_pairs(stream, "seen", 0, [0, 1], ["foreign_driver", "parts"])
    for variant in ("foreign_driver", "parts"):
        for key, value in alone[variant].items():
            np.testing.assert_array_equal(value, beside[variant][key], err_msg=f"{variant} {key}")
