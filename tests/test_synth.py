"""Synthetic data: Anny identities, posing, procedural actions and filmstrip rendering.

Uses the smallest topology (369 vertices). The first Anny build on a machine takes minutes
and writes the cache under ~/.cache/anny; later builds take well under a second.
"""

import numpy as np
import pytest
import torch

from aniformer.io.render import render_filmstrip
from aniformer.synth.bodies import PHENOTYPE_KEYS, TOPOLOGIES, BodyModel, sample_identities
from aniformer.synth.motions import ACTIONS, Motion, sample_motion
from aniformer.synth.rig import CONTROLLED_PARENTS

FRAMES = 30
# Bound on any vertex's move between consecutive frames of a 30-frame clip. The fastest limb
# is the hand in jumping jacks: a ~0.65 m arm sweeping ~2.4 rad and back up to 1.25 times per
# clip peaks at 0.65 * 1.2 * 2 * pi * 1.25 / 30 ~ 0.2 m per frame; a broken pose (a limb
# flipping through the body) jumps by a metre or more.
MAX_STEP_M = 0.25
# A clip must move: some vertex strays at least this far from its mean position.
MIN_MOTION_M = 0.03


@pytest.fixture(scope="module")
def body():
    return BodyModel("notoes_collapse3pc")


def test_topologies_and_faces(body):
    assert body.num_vertices == TOPOLOGIES["notoes_collapse3pc"] == 369
    assert body.faces.dtype == np.int64 and body.faces.shape[1] == 3
    assert body.faces.min() == 0 and body.faces.max() == body.num_vertices - 1
    assert BodyModel("notoes_collapse3pc")._model is body._model  # built once per process


def test_unknown_topology():
    with pytest.raises(ValueError, match="notoes_collapse10pc"):
        BodyModel("smpl")


def test_identities_seeded_and_adult():
    a, b = sample_identities(16, seed=3), sample_identities(16, seed=3)
    assert a.shape == (16, len(PHENOTYPE_KEYS)) and a.dtype == np.float32
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, sample_identities(16, seed=4))
    assert np.all((a >= 0) & (a <= 1))
    # Anny age 0.5 is 25 years and 1.0 is 90; 18 years maps just under 0.5.
    assert a[:, PHENOTYPE_KEYS.index("age")].min() > 0.4


def test_pose_batched_deterministic(body):
    n = 3
    identities = sample_identities(n, seed=0)
    rotvecs = np.random.default_rng(0).normal(0, 0.2, (n, len(body.bone_labels), 3))
    translation = np.array([[0, 0, 0], [0, 0, 1], [1, 0, 0]], np.float32)
    v = body.pose(identities, rotvecs, translation)
    assert v.shape == (n, body.num_vertices, 3) and v.dtype == np.float32
    np.testing.assert_array_equal(v, body.pose(identities, rotvecs, translation))
    single = body.pose(identities[1:2], rotvecs[1:2], translation[1:2])
    np.testing.assert_allclose(single[0], v[1], atol=1e-5)
    np.testing.assert_allclose(body.pose(identities, rotvecs) + translation[:, None], v, atol=1e-6)


def test_zero_rotvecs_give_anny_rest_mesh(body):
    identities = sample_identities(2, seed=1)
    v = body.pose(identities, np.zeros((2, len(body.bone_labels), 3), np.float32))
    phenotypes = {k: torch.from_numpy(identities[:, i]) for i, k in enumerate(PHENOTYPE_KEYS)}
    expected = body._model(phenotype_kwargs=phenotypes)["vertices"].detach().numpy()
    np.testing.assert_allclose(v, expected, atol=1e-6)
    height = v[..., 2].max(1) - v[..., 2].min(1)
    assert np.all((height > 1.3) & (height < 2.1))  # metres, z up


def test_controlled_bone_hierarchy_matches_rig(body):
    def ancestors(bone):
        index = body.bone_labels.index(bone)
        while body.bone_parents[index] >= 0:
            index = body.bone_parents[index]
            yield body.bone_labels[index]

    for bone, parent in CONTROLLED_PARENTS.items():
        controlled = [a for a in ancestors(bone) if a in CONTROLLED_PARENTS]
        assert (controlled[0] if controlled else None) == parent, bone


def test_unknown_action(body):
    with pytest.raises(ValueError, match="jumping_jacks"):
        sample_motion("moonwalk", 0, body.bone_labels)


@pytest.mark.parametrize("action", ACTIONS)
def test_action(body, action):
    m = sample_motion(action, 7, body.bone_labels, frames=FRAMES)
    assert isinstance(m, Motion) and m.action == action and m.seed == 7
    assert m.rotvecs.shape == (FRAMES, len(body.bone_labels), 3) and m.rotvecs.dtype == np.float32
    assert m.translation.shape == (FRAMES, 3) and m.translation.dtype == np.float32
    again = sample_motion(action, 7, body.bone_labels, frames=FRAMES)
    np.testing.assert_array_equal(m.rotvecs, again.rotvecs)
    np.testing.assert_array_equal(m.translation, again.translation)
    assert not np.allclose(m.rotvecs, sample_motion(action, 8, body.bone_labels, FRAMES).rotvecs)

    identity = np.repeat(sample_identities(1, seed=2), FRAMES, axis=0)
    v = body.pose(identity, m.rotvecs, m.translation)
    assert np.isfinite(v).all()
    assert np.linalg.norm(np.diff(v, axis=0), axis=-1).max() < MAX_STEP_M
    assert np.linalg.norm(v - v.mean(0), axis=-1).max() > MIN_MOTION_M


def test_render_filmstrip(body, tmp_path):
    m = sample_motion("jumping_jacks", 0, body.bone_labels, frames=6)
    v = body.pose(np.repeat(sample_identities(1, 0), 6, axis=0), m.rotvecs, m.translation)
    path = render_filmstrip([("a", v, body.faces), ("b", v[:3], body.faces)], tmp_path / "s.png", frames=4, title="test")
    assert path == tmp_path / "s.png"
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 1000
    assert [p.name for p in tmp_path.iterdir()] == ["s.png"]


def test_library_windows_longer_than_stride_3_allows_take_smaller_strides(body):
    """A 60-frame library clip holds a 20-frame window at stride 3 at most: 24 frames (the foreign-driver
    clips of synth.variants) take strides 1-2, and the 3-frame training windows draw exactly as before."""
    from aniformer.synth.poses import LIBRARY_FRAMES, LIBRARY_INSTANCES, _library, _library_clip

    actions = ACTIONS[:3]
    rotvecs, translation = _library([np.random.default_rng(k) for k in range(40)], 24, body.bone_labels, actions)
    assert rotvecs.shape == (40 * 24, len(body.bone_labels), 3) and translation.shape == (40 * 24, 3)
    for seed in range(20):  # T = 3: the window the draws always gave (a stride in 1-3)
        got, _ = _library([np.random.default_rng(seed)], 3, body.bone_labels, actions)
        rng = np.random.default_rng(seed)
        clip = _library_clip(actions[rng.integers(len(actions))], int(rng.integers(LIBRARY_INSTANCES)),
                             tuple(body.bone_labels))
        stride = int(rng.integers(1, 4))
        start = int(rng.integers(LIBRARY_FRAMES - 2 * stride))
        np.testing.assert_array_equal(got.numpy(), clip.rotvecs[start:start + 2 * stride + 1:stride])
    with pytest.raises(ValueError, match=f"at most {LIBRARY_FRAMES} frames"):
        _library([np.random.default_rng(0)], LIBRARY_FRAMES + 1, body.bone_labels, actions)
