"""pipeline/data.py and jobs/generate_data.py: the synthetic mesh bank, pairs, splits, the CLI.

Generation and the Ray Data paths run on the session's real local multi-node Ray cluster
(tests/conftest.py); the numpy paths (plans, pair assembly, the mesh-folder reader) need no Ray.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from aniformer.cli.args import load_config
from aniformer.config import from_dict
from aniformer.errors import UserError
from pipeline import data

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "configs" / "tiny.yaml"


def tiny_cfg(**overrides) -> data.DataConfig:
    section = dict(load_config(TINY)["data"], **overrides)
    return from_dict(data.DataConfig, section, "data")


def files_of(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="session")
def tiny_bank(ray_cluster, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("banks") / "tiny"
    data.generate_bank(tiny_cfg(), out, workers=2, progress=False)
    return out


@pytest.fixture(scope="session")
def tiny_loaded(tiny_bank) -> data.Bank:
    return data.load_bank(tiny_bank, verify=True)


def sampler(bank: data.Bank, **kw) -> data.PairSampler:
    return data.PairSampler(bank, **dict(tiny_cfg().pair_settings(), **kw))


# ---------------------------------------------------------------------------------------------
# Config and splits (no Ray)
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "override, words",
    [
        ({"topology": "smpl"}, "topology"),
        ({"window": 0}, "window"),
        ({"window": 31}, "window"),
        ({"frames": "many"}, "frames"),
        ({"shuffle": "all"}, "shuffle"),
        ({"center": "origin"}, "center"),
        ({"actions": ["moonwalk"]}, "unknown action"),
        ({"heldout_actions": ["hips"]}, "heldout_actions"),
        ({"heldout_actions": ["jumping_jacks", "punching", "knee_raises", "shake_arms"]}, "heldout_actions"),
        ({"unseen_driving_identities": 3}, "unseen_driving_identities"),
        ({"unseen_instance_fraction": 1.0}, "unseen_instance_fraction"),
        ({"target_identities_train": 0}, "target_identities_train"),
        ({"pairs_per_epoch": -5}, "pairs_per_epoch"),
        ({"shard_mb": 0}, "shard_mb"),
        ({"colour": "red"}, "unknown key"),
    ],
)
def test_bad_config_is_one_line_user_error(override, words):
    with pytest.raises(UserError) as e:
        tiny_cfg(**override)
    message = str(e.value)
    assert words in message and "\n" not in message


@pytest.mark.parametrize("config", ["tiny.yaml", "default.yaml", "paper.yaml", "pretrained.yaml"])
def test_every_section_goes_to_its_dict_and_back_unchanged(config):
    """One config <-> dict path (aniformer.config): YAML lists become tuples inside, lists again outside."""
    import yaml

    from pipeline.run_spec import RunSpec

    spec = RunSpec.from_config(load_config(ROOT / "configs" / config))
    as_dict = spec.to_dict()
    assert yaml.safe_load(yaml.safe_dump(as_dict)) == as_dict  # plain values only
    assert RunSpec.from_config(as_dict) == spec
    assert isinstance(spec.train.milestones, tuple) and isinstance(as_dict["train"]["milestones"], list)


def test_the_window_is_set_once_in_data():
    from pipeline.run_spec import RunSpec

    assert RunSpec.from_config(load_config(TINY)).model.window == 3  # tiny.yaml's model section has none
    assert RunSpec.from_config(load_config(TINY, ["data.window=5"])).model.window == 5
    assert RunSpec.from_config(load_config(TINY, ["model.window=5", "data.window=5"])).model.window == 5
    with pytest.raises(UserError, match=r"model.window=4 differs from data.window=3: set the window once, in data.window"):
        RunSpec.from_config(load_config(TINY, ["model.window=4"]))


def test_heldout_actions_as_a_count_is_seeded():
    a = tiny_cfg(heldout_actions=2).resolved_actions()[1]
    assert len(a) == 2 and a == tiny_cfg(heldout_actions=2).resolved_actions()[1]


@pytest.mark.parametrize("config", ["tiny.yaml", "bank.yaml", "paper.yaml"])
def test_splits_disjoint_and_complete(config):
    cfg = data.data_config(load_config(ROOT / "configs" / config))
    plan = data.plan_bank(cfg)
    ids, motions, splits = plan.identities, plan.motions, plan.splits
    role = {i["id"]: (i["role"], i["split"]) for i in ids}
    # identities: drivers seen/unseen and targets train/test partition the identities
    groups = [
        {i for i, r in role.items() if r == g}
        for g in [("driver", "seen"), ("driver", "unseen"), ("target", "train"), ("target", "test")]
    ]
    assert sum(map(len, groups)) == len(ids) == len(set().union(*groups))
    assert [len(g) for g in groups] == [
        cfg.driving_identities - cfg.unseen_driving_identities,
        cfg.unseen_driving_identities,
        cfg.target_identities_train,
        cfg.target_identities_test,
    ]
    # motion instances: every one in exactly one split; the splits' motion sets are disjoint
    seen_motion_sets = [set(s["motions"]) for name, s in splits.items() if name != "seen"]
    assert sum(map(len, seen_motion_sets)) == len(motions) == len(set().union(*seen_motion_sets))
    assert splits["seen"]["motions"] == splits["train"]["motions"]
    # train and unseen split the seen drivers' instances of the regular actions: the documented share
    # (unseen_instance_fraction, at least one when positive, never all) is unseen, the rest trains
    _, heldout = cfg.resolved_actions()
    eligible = {m["id"] for m in motions if role[m["driver"]] == ("driver", "seen") and m["action"] not in heldout}
    assert set(splits["train"]["motions"]) | set(splits["unseen"]["motions"]) == eligible
    n, fraction = len(eligible), cfg.unseen_instance_fraction
    unseen = min(n - 1, max(1, round(fraction * n))) if fraction > 0 and n >= 2 else 0
    assert (len(splits["train"]["motions"]), len(splits["unseen"]["motions"])) == (n - unseen, unseen)
    assert n - unseen >= 1  # there is something to train on
    # targets: train split uses train targets only; every evaluation split uses test targets only
    assert set(splits["train"]["targets"]) == groups[2]
    for name in ("seen", "unseen", "unseen_drivers", "heldout_actions"):
        assert set(splits[name]["targets"]) == groups[3]
    # what each split holds out
    by_id = {m["id"]: m for m in motions}
    for m in splits["train"]["motions"] + splits["unseen"]["motions"]:
        assert role[by_id[m]["driver"]] == ("driver", "seen") and by_id[m]["action"] not in heldout
    for m in splits["unseen_drivers"]["motions"]:
        assert role[by_id[m]["driver"]] == ("driver", "unseen") and by_id[m]["action"] not in heldout
    assert {by_id[m]["action"] for m in splits["heldout_actions"]["motions"]} == set(heldout)
    # the bank holds exactly the sequences pairs can need
    have = set(zip(plan.sequences["identity"], plan.sequences["motion"], strict=True))
    need = {(m["driver"], m["id"]) for m in motions}
    for s in splits.values():
        need |= {(t, m) for t in s["targets"] for m in s["motions"]}
    assert have == need
    assert plan.counts["meshes"] == cfg.frames * len(have)


# ---------------------------------------------------------------------------------------------
# Generation on the Ray cluster
# ---------------------------------------------------------------------------------------------


def test_bank_layout(tiny_bank, tiny_loaded):
    import pyarrow.parquet as pq

    from aniformer.synth.bodies import BodyModel

    m = tiny_loaded.manifest
    cfg = tiny_cfg()
    assert m.schema_version == data.SCHEMA_VERSION and m.topology == cfg.topology
    assert tiny_loaded.vertices.shape == (m.counts["meshes"], 369, 3)
    assert tiny_loaded.vertices.dtype == np.float32 and np.isfinite(tiny_loaded.vertices).all()
    np.testing.assert_array_equal(tiny_loaded.faces, BodyModel(cfg.topology).faces)
    schema = pq.read_schema(tiny_bank / m.shards[0]["path"])
    assert str(schema.field("vertices").type) == "fixed_size_list<element: float>[1107]"
    assert m.config["seed"] == cfg.seed and "workers" not in m.config
    table = pq.read_table(tiny_bank / m.shards[-1]["path"])
    last = table.slice(table.num_rows - 1).to_pylist()[0]
    assert last["sequence"] == m.counts["sequences"] - 1 and last["frame"] == cfg.frames - 1
    assert not list(tiny_bank.rglob(".*"))  # no temporary files left


def test_generation_is_deterministic_across_worker_counts(tiny_bank, tmp_path):
    again = tmp_path / "again"
    data.generate_bank(tiny_cfg(), again, workers=1, progress=False)
    first, second = files_of(tiny_bank), files_of(again)
    assert first.keys() == second.keys() and len(first) >= 3
    for name in first:
        assert first[name] == second[name], name


def test_seed_changes_the_bank(tiny_loaded, ray_cluster, tmp_path):
    other = data.generate_bank(tiny_cfg(seed=1, instances_per_action=1), tmp_path / "b", progress=False)
    assert other.identities[0]["phenotype"] != tiny_loaded.manifest.identities[0]["phenotype"]


@pytest.fixture
def one_torch_thread():
    """Torch on one thread for a test, as pipeline/data/synthetic.py's generate_shard poses the bank."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_ground_truth_is_anny_target_shape_with_driving_pose(tiny_loaded, one_torch_thread):
    """Bit for bit. Anny's float32 output depends (at the last bit) on the batch size and the thread
    count, so the bank poses one whole clip per call on one thread; the reference here does the same
    and slices the window (with two threads, 55 % of the coordinates differed in the last bit on a
    Xeon of 2026-12-02)."""
    from aniformer.geometry import center_bbox
    from aniformer.synth.bodies import BodyModel
    from aniformer.synth.motions import sample_motion

    m = tiny_loaded.manifest
    body = BodyModel(m.topology)
    s = sampler(tiny_loaded, shuffle="none", center="none")
    for split in ("train", "unseen", "heldout_actions"):
        b = s.batch(split, 0, np.arange(4))
        for k in range(4):
            spec = m.motions[int(b["motion"][k])]
            motion = sample_motion(spec["action"], spec["seed"], body.bone_labels, frames=spec["frames"])
            window = slice(int(b["start"][k]), int(b["start"][k]) + s.window)
            for key, ident in (
                ("ground_truth", b["target_identity"][k]),
                ("driving", b["driving_identity"][k]),
            ):
                phenotype = np.asarray(m.identities[int(ident)]["phenotype"], np.float32)
                clip = body.pose(np.repeat(phenotype[None], spec["frames"], 0), motion.rotvecs, motion.translation)
                np.testing.assert_array_equal(b[key][k], clip[window])
    # and, bounding-box centred per mesh, exactly what the default sampler returns
    c = sampler(tiny_loaded, shuffle="none").batch("train", 3, [5])
    raw = sampler(tiny_loaded, shuffle="none", center="none").batch("train", 3, [5])
    for key in ("driving", "target", "ground_truth"):
        np.testing.assert_array_equal(c[key], center_bbox(raw[key]))
        np.testing.assert_allclose((c[key].min(-2) + c[key].max(-2)) / 2, 0, atol=1e-6)
    # center="window": one offset per window (keeps the motion's own translation within it)
    w = sampler(tiny_loaded, shuffle="none", center="window").batch("train", 3, [5])
    for key in ("driving", "ground_truth"):
        np.testing.assert_array_equal(w[key][0], center_bbox(raw[key][0].reshape(-1, 3)).reshape(raw[key][0].shape))
    np.testing.assert_array_equal(w["target"], c["target"])


def test_target_is_target_identity_at_a_frame_of_a_split_motion(tiny_loaded):
    s = sampler(tiny_loaded, shuffle="none", center="none")
    table = s.pair_table("train", 0)
    b = s.batch("train", 0, np.arange(16))
    train_motions = set(tiny_loaded.manifest.splits["train"]["motions"])
    for k in range(16):
        seq = tiny_loaded.sequence(int(table["target_identity"][k]), int(table["target_pose_motion"][k]))
        np.testing.assert_array_equal(b["target"][k], seq[table["target_pose_frame"][k]])
        assert int(table["target_pose_motion"][k]) in train_motions


def test_pairs_are_seeded_by_seed_and_epoch(tiny_loaded):
    s = sampler(tiny_loaded)
    a, again, other = (
        s.batch("train", 0, range(8)),
        sampler(tiny_loaded).batch("train", 0, range(8)),
        s.batch("train", 1, range(8)),
    )
    for key in a:
        np.testing.assert_array_equal(a[key], again[key])
    assert not np.array_equal(a["ground_truth"], other["ground_truth"])
    # a pair does not depend on which batch assembles it
    single = s.batch("train", 0, [5])
    for key in a:
        np.testing.assert_array_equal(single[key][0], a[key][5])


def _triangles(vertices: np.ndarray, faces: np.ndarray) -> set:
    tri = vertices[faces]  # (F, 3, 3)
    return {tuple(sorted(map(tuple, t.round(6).tolist()))) for t in tri}


@pytest.mark.parametrize("mode", ["target", "both"])
def test_shuffling_keeps_faces_consistent_and_target_aligned(tiny_loaded, mode):
    from aniformer.geometry import shuffle_vertices

    plain = sampler(tiny_loaded, shuffle="none").batch("seen", 0, np.arange(4))
    mixed = sampler(tiny_loaded, shuffle=mode).batch("seen", 0, np.arange(4))
    table = sampler(tiny_loaded, shuffle=mode).pair_table("seen", 0)
    faces = tiny_loaded.faces
    V = tiny_loaded.num_vertices
    for k in range(4):
        tf = mixed["target_faces"][k]
        assert not np.array_equal(tf, faces)
        # same surface: the same triangles, as sets of positions, for the target and every GT frame
        assert _triangles(mixed["target"][k], tf) == _triangles(plain["target"][k], faces)
        for t in range(mixed["ground_truth"].shape[1]):
            assert _triangles(mixed["ground_truth"][k, t], tf) == _triangles(plain["ground_truth"][k, t], faces)
        # target and ground truth share one permutation, the one aniformer.geometry.shuffle_vertices applies
        rng = np.random.default_rng(int(table["perm_seed"][k]))
        perm = rng.permutation(V)
        v, f = shuffle_vertices(plain["target"][k], faces, perm)
        np.testing.assert_array_equal(mixed["target"][k], v)
        np.testing.assert_array_equal(tf, f)
        np.testing.assert_array_equal(mixed["ground_truth"][k], plain["ground_truth"][k][:, perm])
        if mode == "target":
            np.testing.assert_array_equal(mixed["driving"][k], plain["driving"][k])
        else:
            driver_perm = rng.permutation(V)
            assert not np.array_equal(driver_perm, perm)
            np.testing.assert_array_equal(mixed["driving"][k], plain["driving"][k][:, driver_perm])


def test_motion_is_smooth(tiny_loaded):
    """Consecutive frames of every sequence move a little and smoothly (no jumps, no jitter)."""
    m = tiny_loaded.manifest
    for s, first in enumerate(m.sequences["first_row"]):
        seq = tiny_loaded.vertices[first : first + m.sequences["frames"][s]].astype(np.float64)
        velocity = np.diff(seq, axis=0)
        speed = np.linalg.norm(velocity, axis=-1)
        accel = np.linalg.norm(np.diff(velocity, axis=0), axis=-1)
        assert speed.max() < 0.3, f"sequence {s}: a vertex jumps {speed.max():.3f} m between frames"
        assert speed.mean() > 1e-3, f"sequence {s} hardly moves"
        # white-noise jitter would give accel/speed ~ 1.2; smooth periodic motion much less
        assert accel.mean() < 0.9 * speed.mean(), f"sequence {s}: jittery ({accel.mean() / speed.mean():.2f})"


def test_bank_config_mismatch_is_refused(tiny_bank):
    with pytest.raises(UserError, match="topology"):
        data.PairSampler.from_dir(tiny_bank, tiny_cfg(topology="notoes_collapse5pc"))
    s = data.PairSampler.from_dir(tiny_bank, tiny_cfg(shuffle="both", window=5))  # pair settings may differ
    assert s.window == 5 and s.batch("train", 0, [0])["driving"].shape == (1, 5, 369, 3)
    with pytest.raises(UserError, match="unknown split"):
        s.split("validation")


def test_pair_source_of_a_bank_names_its_splits_in_the_pipelines_order(tiny_bank, tiny_loaded):
    import dataclasses

    source = data.pair_source(tiny_cfg(), tiny_bank)  # a directory: loaded and checked against the config
    assert isinstance(source, data.PairSource) and isinstance(source, data.PairSampler)
    assert list(source.splits) == list(data.BANK_SPLITS) == source.non_empty_splits
    assert source.splits["unseen"] == data.BANK_SPLITS["unseen"][2]
    splits = {**tiny_loaded.manifest.splits, "unseen": {**tiny_loaded.manifest.splits["unseen"], "targets": []},
              "extra": {"motions": [0], "targets": [0]}}
    bank = dataclasses.replace(tiny_loaded, manifest=dataclasses.replace(tiny_loaded.manifest, splits=splits))
    other = data.pair_source(tiny_cfg(topology="notoes_collapse5pc"), bank)  # a Bank in memory: taken as it is
    assert other.non_empty_splits == [s for s in data.BANK_SPLITS if s != "unseen"] + ["extra"]
    with pytest.raises(UserError, match="empty"):
        other.split("unseen")
    wider = other.with_settings(window=5, shuffle="none")
    assert wider.bank is bank and (wider.window, wider.shuffle, wider.seed) == (5, "none", other.seed)


# ---------------------------------------------------------------------------------------------
# Pairs through Ray Data / Ray Train
# ---------------------------------------------------------------------------------------------


def test_pair_dataset_matches_numpy_sampler(tiny_bank, tiny_loaded):
    import torch

    ds = data.pair_dataset(tiny_bank, "train", epochs=2, first_epoch=3, pairs=24, batch_size=8)
    rows = {}
    for batch in ds.iter_torch_batches(batch_size=8):
        assert batch["driving"].dtype == torch.float32 and batch["target_faces"].dtype == torch.int64
        assert batch["driving"].shape[1:] == (3, 369, 3) and batch["target"].shape[1:] == (369, 3)
        assert batch["ground_truth"].shape[1:] == (3, 369, 3) and batch["target_faces"].shape[1:] == (734, 3)
        for k in range(len(batch["index"])):
            rows[(int(batch["epoch"][k]), int(batch["index"][k]))] = {key: v[k].numpy() for key, v in batch.items()}
    assert sorted(rows) == [(e, i) for e in (3, 4) for i in range(24)]
    s = sampler(tiny_loaded)
    for epoch in (3, 4):
        expected = s.batch("train", epoch, np.arange(24), n=24)
        for i in range(24):
            for key in ("driving", "target", "ground_truth", "target_faces"):
                np.testing.assert_array_equal(rows[(epoch, i)][key], expected[key][i])


def test_pair_dataset_bad_split(tiny_bank):
    with pytest.raises(UserError, match="unknown split"):
        data.pair_dataset(tiny_bank, "nope")


@pytest.mark.slow
def test_ray_train_reads_pairs_through_dataset_shards(tiny_bank, tmp_path):
    import json

    import ray.train
    from ray.train import ScalingConfig
    from ray.train.torch import TorchTrainer

    def loop(config):
        shard = ray.train.get_dataset_shard("train")
        seen = []
        for batch in shard.iter_torch_batches(batch_size=4):
            assert batch["driving"].shape[1:] == (3, 369, 3) and batch["target_faces"].shape[1:] == (734, 3)
            seen += (batch["epoch"] * 1000 + batch["index"]).tolist()
        rank = ray.train.get_context().get_world_rank()
        (Path(config["out"]) / f"rank{rank}.json").write_text(json.dumps(seen))

    ds = data.pair_dataset(tiny_bank, "train", epochs=2, pairs=16, batch_size=4)
    trainer = TorchTrainer(
        loop,
        train_loop_config={"out": str(tmp_path)},
        datasets={"train": ds},
        scaling_config=ScalingConfig(num_workers=2, resources_per_worker={"CPU": 0.5}),
        run_config=ray.train.RunConfig(storage_path=str(tmp_path / "runs"), name="feed"),
    )
    trainer.fit()
    seen = [json.loads((tmp_path / f"rank{r}.json").read_text()) for r in (0, 1)]
    assert seen[0] and seen[1]  # both workers got pairs, no pair twice, every pair of both epochs
    assert sorted(seen[0] + seen[1]) == [e * 1000 + i for e in (0, 1) for i in range(16)]


# ---------------------------------------------------------------------------------------------
# The job
# ---------------------------------------------------------------------------------------------


def run_job(*args, env=None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(ROOT / "jobs" / "generate_data.py"), *map(str, args)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env=dict(os.environ, **(env or {})),
        timeout=300,
    )


@pytest.mark.parametrize(
    "args, words",
    [
        (["--config", TINY, "data.window=0"], "window"),
        (["--config", TINY, "frames=1"], "frames"),
        (["--config", TINY, "data.colour=red"], "unknown key"),
        (["--config", TINY, "notakeyvalue"], "key=value"),
        (["--config", TINY, "--workers", "0"], "--workers"),
        (["--config"], "--config"),
    ],
)
def test_job_bad_input_exits_2_with_one_line(tmp_path, capsys, job_main, args, words):
    from aniformer.cli.exits import run

    with pytest.raises(SystemExit) as exit_:
        run(job_main("generate_data"), [*map(str, args), "--out", str(tmp_path / "out")])
    stderr = capsys.readouterr().err
    assert exit_.value.code == 2 and stderr.strip().count("\n") == 0 and words in stderr, stderr
    assert not (tmp_path / "out").exists()


def test_job_bad_input_exits_2_from_the_shell(tmp_path):
    r = run_job("--config", "missing.yaml", "--out", tmp_path / "out")
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and "config file not found" in r.stderr, r.stderr
    assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_job_generates_refuses_and_overwrites(tiny_bank, ray_address, tmp_path):
    out = tmp_path / "bank"
    env = {"RAY_ADDRESS": ray_address}
    r = run_job("--config", TINY, "--out", out, "--no-progress", env=env)
    assert r.returncode == 0, r.stderr
    assert str(out) in r.stdout
    assert files_of(out) == files_of(tiny_bank)  # same config, same bytes, CLI or library
    r = run_job("--config", TINY, "--out", out, env=env)
    assert r.returncode == 2 and "--overwrite" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    r = run_job(
        "--config",
        TINY,
        "--out",
        out,
        "--overwrite",
        "--no-progress",
        "seed=5",
        "instances_per_action=1",
        env=env,
    )
    assert r.returncode == 0, r.stderr
    assert data.read_manifest(out).config["seed"] == 5
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bank"]  # no temporary directories left


# ---------------------------------------------------------------------------------------------
# Folders of user mesh sequences
# ---------------------------------------------------------------------------------------------


def _write_sequences(root: Path, frames: int = 6) -> dict:
    import trimesh

    base = trimesh.creation.icosphere(subdivisions=1)
    written = {}
    clips = {"subjA": ["subjA_jump", "subjA_wave"], "subjB": ["subjB_jump"]}
    everything = [c for cs in clips.values() for c in cs]
    for ident in ["subjA", "subjB", "t0", "t1", "t2"]:
        for c, clip in enumerate(clips.get(ident, everything)):
            scale = 1.0 + 0.1 * ["subjA", "subjB", "t0", "t1", "t2"].index(ident)
            for f in range(frames):
                v = base.vertices * scale + np.array([0.0, 0.0, 0.05 * f * (c + 1)])
                v[:, 0] *= 1 + 0.02 * f
                path = root / ident / clip / f"frame{f}.obj"  # frame10 sorts after frame9
                path.parent.mkdir(parents=True, exist_ok=True)
                trimesh.Trimesh(v, base.faces, process=False).export(path)
                written[(ident, clip, f)] = v.astype(np.float32)
    return written


def test_import_mesh_sequences(tmp_path):
    written = _write_sequences(tmp_path / "src", frames=6)
    manifest = data.import_mesh_sequences(
        tmp_path / "src",
        tmp_path / "bank",
        frames=4,
        seed=0,
        test_target_fraction=0.34,
        unseen_instance_fraction=0.0,
        progress=False,
    )
    ids = {i["name"]: i for i in manifest.identities}
    assert {n for n, i in ids.items() if i["role"] == "driver"} == {"subjA", "subjB"}
    assert sum(i["split"] == "test" for i in ids.values()) == 1
    assert {m["action"] for m in manifest.motions} == {"jump", "wave"}
    bank = data.load_bank(tmp_path / "bank", verify=True)
    assert bank.vertices.shape[1:] == (42, 3) and manifest.counts["meshes"] == len(bank.vertices)
    by_name = {m["name"]: m["id"] for m in manifest.motions}
    picked = np.round(np.linspace(0, 5, 4)).astype(int)  # 4 of 6 frames, evenly
    seq = bank.sequence(ids["t1"]["id"], by_name["subjB_jump"])
    for k, f in enumerate(picked):
        np.testing.assert_allclose(seq[k], written[("t1", "subjB_jump", int(f))], rtol=0, atol=1e-6)
    s = data.PairSampler(bank, window=3, shuffle="target", seed=0, pairs_per_epoch=8, eval_pairs=4)
    b = s.batch("train", 0, np.arange(8))
    assert b["driving"].shape == (8, 3, 42, 3) and b["target_faces"].shape == (8, 80, 3)
    assert s.batch("seen", 0, np.arange(4))["ground_truth"].shape == (4, 3, 42, 3)


def test_import_rejects_mixed_topologies_and_ambiguous_clips(tmp_path):
    import trimesh

    _write_sequences(tmp_path / "src", frames=3)
    bad = trimesh.creation.icosphere(subdivisions=2)
    bad.export(tmp_path / "src" / "t2" / "subjA_wave" / "frame1.obj")
    with pytest.raises(UserError, match="topology"):
        data.import_mesh_sequences(tmp_path / "src", tmp_path / "bank", progress=False)
    _write_sequences(tmp_path / "src2", frames=3)
    (tmp_path / "src2" / "subjB" / "subjA_wave").mkdir()
    for f in (tmp_path / "src2" / "subjA" / "subjA_wave").iterdir():
        (tmp_path / "src2" / "subjB" / "subjA_wave" / f.name).write_bytes(f.read_bytes())
    with pytest.raises(UserError, match="exactly one"):
        data.import_mesh_sequences(tmp_path / "src2", tmp_path / "bank2", progress=False)
