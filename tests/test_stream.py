"""Pairs made on the fly (aniformer.synth.stream, .poses): determinism, coverage, splits, Ray Data."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from aniformer.synth.bodies import BodyModel
from aniformer.synth.poses import FAMILIES, sample_windows
from aniformer.synth.stream import STREAM_SPLITS, StreamPairs, sample_body_pairs

TOPOLOGY = "notoes_collapse3pc"


@pytest.fixture(scope="module")
def stream() -> StreamPairs:
    return StreamPairs(TOPOLOGY, window=3, seed=0, pairs_per_epoch=32, eval_pairs=8)


@pytest.fixture(scope="module")
def body() -> BodyModel:
    return BodyModel(TOPOLOGY)


def test_pair_is_a_function_of_seed_split_epoch_index_not_of_its_batch(stream):
    whole = stream.batch("train", 3, np.arange(12))
    part = stream.batch("train", 3, [7, 2])
    for key in ("driving", "target", "ground_truth"):  # Anny's float32 skinning: last bits vary with the batch
        np.testing.assert_allclose(part[key], whole[key][[7, 2]], atol=1e-6, rtol=0)
    assert whole["driving"].shape == (12, 3, 369, 3) and whole["target"].shape == (12, 369, 3)
    assert whole["target_faces"].shape == (12, *stream.faces.shape)
    again = StreamPairs(TOPOLOGY, window=3, seed=0).batch("train", 3, [7])
    np.testing.assert_allclose(again["driving"][0], whole["driving"][7], atol=1e-6, rtol=0)
    for other in (stream.batch("train", 4, [7]), stream.batch("seen", 3, [7]),
                  StreamPairs(TOPOLOGY, window=3, seed=1).batch("train", 3, [7])):
        assert not np.allclose(other["driving"][0], whole["driving"][7])


def test_meshes_are_centred_and_ground_truth_is_the_target_body(stream):
    b = stream.batch("seen", 0, np.arange(6))
    for key in ("driving", "ground_truth"):
        centre = (b[key].min(axis=2) + b[key].max(axis=2)) / 2
        assert np.abs(centre).max() < 1e-5
    # the target body is kept: its edge lengths are the ground truth's up to pose (same identity), not the driver's
    faces = stream.faces

    def edges(v):
        return np.linalg.norm(v[..., faces[:, 0], :] - v[..., faces[:, 1], :], axis=-1)

    gt, drv = edges(b["ground_truth"][:, 0]), edges(b["driving"][:, 0])
    target = edges(b["target"])
    assert np.median(np.abs(gt - target)) < np.median(np.abs(drv - target))


def test_splits_are_seeded_apart_and_bodies_follow_their_distribution():
    rngs = [np.random.default_rng(i) for i in range(200)]
    mixed = sample_body_pairs(rngs, "mixed")
    assert mixed.shape == (200, 2, 6) and (0 <= mixed).all() and (mixed <= 1).all()
    free = [2, 3, 4, 5]  # muscle, weight, height, proportions
    assert (mixed[..., free] < 0.05).any() and (mixed[..., free] > 0.95).any()  # the extremes are covered
    extreme = sample_body_pairs([np.random.default_rng(i) for i in range(50)], "extreme")
    assert ((extreme[..., free] <= 0.12) | (extreme[..., free] >= 0.88)).all()
    mismatch = sample_body_pairs([np.random.default_rng(i) for i in range(50)], "mismatch")
    opposite = (mismatch[:, 0, 2:5] > 0.5) != (mismatch[:, 1, 2:5] > 0.5)  # muscle, weight, height
    assert opposite.all()
    streams = {s.stream for s in STREAM_SPLITS.values()}
    assert streams == {"train", "val", "test"} and STREAM_SPLITS["train"].stream == "train"
    assert STREAM_SPLITS["seen"].stream == STREAM_SPLITS["unseen"].stream == "val"
    assert set(STREAM_SPLITS["heldout_actions"].actions).isdisjoint(STREAM_SPLITS["train"].actions)
    assert "kick" in STREAM_SPLITS["heldout_actions"].families and "kick" not in STREAM_SPLITS["train"].families


@pytest.mark.parametrize("family", FAMILIES)
def test_every_family_moves_smoothly(family, body):
    T, B = 6, 4
    rngs = [np.random.default_rng([5, i]) for i in range(B)]
    rotvecs, translation = sample_windows([family] * B, ["upright"] * B, rngs, T, body.bone_labels)
    assert rotvecs.shape == (B, T, len(body.bone_labels), 3) and np.isfinite(rotvecs).all()
    identity = np.repeat(np.full((1, 6), 0.5, np.float32), B * T, 0)
    verts = body.pose(identity, rotvecs.reshape(B * T, -1, 3), translation.reshape(B * T, 3)).reshape(B, T, -1, 3)
    step = np.linalg.norm(np.diff(verts, axis=1), axis=-1).mean(-1)  # mean vertex motion per frame, metres
    assert step.max() < 0.25, f"{family}: frames jump by {step.max():.2f} m"
    assert step.mean() > 1e-3, f"{family}: nothing moves"


def test_orientations_cover_upside_down_and_upright_stays_up(body):
    B = 64
    identity = np.repeat(np.full((1, 6), 0.5, np.float32), B, 0)
    crown = int(body.pose(identity[:1], np.zeros((1, len(body.bone_labels), 3), np.float32))[0, :, 2].argmax())

    def crown_heights(orientation):  # the top of the head above the body's centre, metres
        rngs = [np.random.default_rng([9, i]) for i in range(B)]
        rotvecs, _ = sample_windows(["library"] * B, [orientation] * B, rngs, 1, body.bone_labels)
        verts = body.pose(identity, rotvecs[:, 0])
        return verts[:, crown, 2] - verts[..., 2].mean(1)

    assert (crown_heights("upright") > 0.4).all()
    anywhere = crown_heights("any")
    assert (anywhere < -0.3).mean() > 0.2 and (anywhere > 0.5).mean() < 0.6  # upside down often, upright seldom


def test_residual_model_starts_at_copy_driver_and_needs_one_topology():
    from aniformer.model import AniFormer, AniFormerConfig

    model = AniFormer(AniFormerConfig(channels=(16,), extractor_channels=(8, 16), heads=2, output="residual"))
    driving, target = torch.randn(2, 3, 50, 3), torch.randn(2, 50, 3)
    torch.testing.assert_close(model(driving, target), driving)
    with pytest.raises(ValueError, match="one topology"):
        model(driving, torch.randn(2, 40, 3))
    with pytest.raises(ValueError, match="output must be"):
        AniFormerConfig(output="delta")


def test_stream_config_rejects_shuffling_and_unknown_splits(stream):
    from aniformer.errors import UserError
    from pipeline.data import DataConfig

    with pytest.raises(ValueError, match="shuffle must be none"):
        DataConfig(source="stream", shuffle="target")
    with pytest.raises(ValueError, match="source must be one of"):
        DataConfig(source="s3")
    with pytest.raises(UserError, match="unknown split"):
        stream.batch("nope", 0, [0])


def test_extra_topologies_need_a_stream_and_distinct_anny_topologies():
    from aniformer.errors import UserError
    from pipeline.data import DataConfig, pair_source

    cfg = DataConfig(source="stream", shuffle="none", topology=TOPOLOGY, extra_topologies=["notoes_collapse5pc"])
    assert cfg.train_topologies == (TOPOLOGY, "notoes_collapse5pc")
    assert pair_source(cfg, None, "notoes_collapse5pc").num_vertices == 615
    for extra, message in ((["smpl"], "extra_topologies must be one of"), ([TOPOLOGY], "repeats a topology")):
        with pytest.raises(ValueError, match=message):
            DataConfig(source="stream", shuffle="none", topology=TOPOLOGY, extra_topologies=extra)
    with pytest.raises(ValueError, match="needs source: stream"):
        DataConfig(topology=TOPOLOGY, extra_topologies=["notoes_collapse5pc"])
    with pytest.raises(UserError, match="holds one topology"):
        pair_source(DataConfig(topology=TOPOLOGY), "no-bank", "notoes_collapse5pc")


def test_training_batches_take_the_topologies_in_turn():
    from pipeline.train import interleave

    assert list(interleave([iter("aaa"), iter("bbbb")])) == ["a", "b", "a", "b", "a", "b"]
    assert list(interleave([iter("abc")])) == ["a", "b", "c"]


def test_pair_source_of_a_stream_has_every_split_and_keeps_its_settings():
    from pipeline.data import DataConfig, PairSource, pair_source

    source = pair_source(DataConfig(source="stream", topology=TOPOLOGY, shuffle="none", seed=4), None)
    assert isinstance(source, PairSource) and isinstance(source, StreamPairs)
    assert source.non_empty_splits == list(source.splits) == list(STREAM_SPLITS)
    assert source.splits["crouch"] == STREAM_SPLITS["crouch"].description
    clip = source.with_settings(window=8, eval_pairs=2)
    assert (clip.topology, clip.window, clip.seed, clip.eval_pairs, clip.shuffle) == (TOPOLOGY, 8, 4, 2, "none")
    with pytest.raises(ValueError, match="never shuffled"):
        source.with_settings(shuffle="target")


@pytest.mark.ray
def test_ray_dataset_of_a_stream_holds_the_numpy_pairs(ray_cluster, stream):
    from pipeline.data import pair_dataset

    ds = pair_dataset(stream, "train", epochs=2, pairs=10)
    rows = sorted(ds.iter_rows(), key=lambda r: (r["epoch"], r["index"]))
    assert [(r["epoch"], r["index"]) for r in rows] == [(e, i) for e in range(2) for i in range(10)]
    expected = stream.batch("train", 1, [4])
    np.testing.assert_allclose(rows[14]["driving"], expected["driving"][0], atol=1e-6)
    np.testing.assert_allclose(rows[14]["ground_truth"], expected["ground_truth"][0], atol=1e-6)
    # another topology's share of each epoch: its own pairs (ids from first_index), its own vertices
    other = StreamPairs("notoes_collapse5pc", window=stream.window, seed=stream.seed)
    rows = sorted(pair_dataset(other, "train", epochs=2, pairs=3, first_index=10).iter_rows(),
                  key=lambda r: (r["epoch"], r["index"]))
    assert [(r["epoch"], r["index"]) for r in rows] == [(e, i) for e in range(2) for i in range(10, 13)]
    assert rows[0]["driving"].shape == (3, 615, 3)
    np.testing.assert_allclose(rows[4]["driving"], other.batch("train", 1, [11])["driving"][0], atol=1e-6)


def test_deformation_transfer_keeps_the_target_build_in_the_driver_pose(stream):
    """The geometric prior alone beats both trivial baselines by far on fresh bodies and poses, and the
    transfer model starts exactly there (its correction layer is zero at initialisation)."""
    from aniformer.metrics import pmd
    from aniformer.model import AniFormer, AniFormerConfig
    from aniformer.transfer import deformation_transfer

    b = stream.batch("build_mismatch", 0, np.arange(8))
    driving, target, truth = (torch.from_numpy(b[k]) for k in ("driving", "target", "ground_truth"))
    faces = torch.from_numpy(stream.faces)
    moved = deformation_transfer(driving, target, faces)
    copy, static = pmd(driving, truth), pmd(target[:, None].expand_as(truth), truth)
    assert pmd(moved, truth) < 0.25 * min(copy, static)
    # a driver of the target's own build leaves only the pose's error (one rotation per vertex): ~2 cm RMS here
    assert pmd(deformation_transfer(truth, target, faces), truth) < 0.1 * copy
    model = AniFormer(AniFormerConfig(channels=(16,), extractor_channels=(8, 16), heads=2, output="transfer"))
    torch.testing.assert_close(model(driving, target, faces), moved)
    with pytest.raises(ValueError, match="needs the faces"):
        model(driving, target)


STREAM_TINY = ["data.source=stream", "data.shuffle=none", "data.pairs_per_epoch=16", "data.eval_pairs=4",
               "train.epochs=1", "model.output=transfer", "model.heads=2"]


@pytest.mark.slow
@pytest.mark.ray
def test_train_and_evaluate_on_the_stream_end_to_end(ray_cluster, tmp_path, monkeypatch, job_main, repo_root, capsys,
                                                      scoring):
    """jobs/train.py on pairs made on the fly (no bank is written), then jobs/evaluate.py on its
    checkpoint: every stream split, the model beside the three baselines."""
    import csv
    import json

    from aniformer.cli.exits import run

    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    out = tmp_path / "run"
    run(job_main("train"), ["--config", str(repo_root / "configs/tiny.yaml"), "--out", str(out), *STREAM_TINY,
                            "data.extra_topologies=[notoes_collapse5pc]"])
    assert (out / "best.pt").is_file() and not (out / "bank").exists()
    assert "trained run: epoch 1" in capsys.readouterr().out
    # trained on both topologies, validated on each; the best checkpoint is chosen by their mean
    import mlflow

    (logged,) = mlflow.search_runs(search_all_experiments=True, output_format="list")
    metrics = logged.data.metrics
    for split in ("seen", "unseen"):
        each = [metrics[f"pmd_{split}_{t}"] for t in (TOPOLOGY, "notoes_collapse5pc")]
        assert metrics[f"pmd_{split}"] == pytest.approx(np.mean(each)) and min(each) > 0
    run(job_main("evaluate"), ["--checkpoint", str(out / "best.pt"), "--out", str(tmp_path / "eval"), "--pairs", "2",
                               "--splits", "seen,rotated,build_mismatch", "--clip-frames", "6", "--clip-pairs", "1",
                               "--no-mlflow", "--no-progress"])
    rows = {r["method"]: r for r in csv.DictReader((tmp_path / "eval" / "results.csv").open())}
    assert list(rows) == ["AniFormer", "copy-driver", "static target", "deformation transfer"]
    result = json.loads((tmp_path / "eval" / "results.json").read_text())
    assert (result["clip_frames"], result["clip_pairs"]) == (6, 1) and set(result["acceleration"]) == set(rows)
    assert all(set(v) == {"seen", "rotated", "build_mismatch"} for v in result["acceleration"].values())
    markdown = (tmp_path / "eval" / "results.md").read_text()
    ratio = float(rows["AniFormer"]["seen"]) / float(rows["deformation transfer"]["seen"])
    assert f"| AniFormer ÷ transfer | {ratio:.2f} |" in markdown and "Acceleration error (mm/frame²" in markdown
    # the model's and the copy-driver's rows are their PMD on the same 2 stream pairs, recomputed here
    from aniformer.checkpoint import model_from_checkpoint
    from aniformer.synth.stream import StreamPairs

    model, state = model_from_checkpoint(out / "best.pt")
    data = state["config"]["data"]
    stream = StreamPairs(data["topology"], window=model.config.window, center=data["center"], seed=data["seed"],
                         eval_pairs=2)
    for split in ("seen", "rotated", "build_mismatch"):
        assert float(rows["copy-driver"][split]) == pytest.approx(scoring.pmd(stream, split, 2), rel=1e-4)
        assert float(rows["AniFormer"][split]) == pytest.approx(
            scoring.pmd(stream, split, 2, scoring.model_predict(model), model.config.output_frames()), rel=1e-4)
    # the trivial baselines are far from the truth on mismatched builds; the prior is not
    mismatch = {name: float(r["build_mismatch"]) for name, r in rows.items()}
    assert mismatch["deformation transfer"] < 0.5 * min(mismatch["copy-driver"], mismatch["static target"])
    run(job_main("evaluate"), ["--checkpoint", str(out / "best.pt"), "--out", str(tmp_path / "e615"), "--pairs", "1",
                               "--splits", "seen", "--clip-frames", "0", "--topology", "notoes_collapse5pc",
                               "--no-mlflow", "--no-progress"])  # scored on one of the topologies it trained on
    assert "stream, topology notoes_collapse5pc" in (tmp_path / "e615" / "results.md").read_text()
    with pytest.raises(SystemExit):  # a bank split on a stream checkpoint: one line, exit 2
        run(job_main("evaluate"), ["--checkpoint", str(out / "best.pt"), "--out", str(tmp_path / "e2"),
                                   "--splits", "unseen_drivers", "--no-mlflow", "--no-progress"])
    assert "unknown split(s) unseen_drivers" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # too short a clip for an acceleration: one line, exit 2
        run(job_main("evaluate"), ["--checkpoint", str(out / "best.pt"), "--out", str(tmp_path / "e3"),
                                   "--clip-frames", "2", "--no-mlflow", "--no-progress"])
    assert "--clip-frames must be 0 (none) or >= 3" in capsys.readouterr().err
    # the README's flow: a stream clip as OBJ files, animated with the checkpoint
    samples, anim = tmp_path / "walk", tmp_path / "anim"
    run(job_main("export_meshes"), ["--stream", "notoes_collapse3pc", "--split", "locomotion", "--frames", "5",
                                    "--out", str(samples)])
    assert len(list((samples / "driving").glob("*.obj"))) == 5 and (samples / "target.obj").is_file()
    run(job_main("animate"), ["--checkpoint", str(out / "best.pt"), "--target", str(samples / "target.obj"),
                              "--driving", str(samples / "driving"), "--out", str(anim), "--no-progress"])
    assert len(list((anim / "frames").glob("*.obj"))) == 5 and (anim / "animation.glb").is_file()
