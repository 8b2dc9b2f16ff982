"""PMD over splits, the noise sweep and jobs/evaluate.py end to end on the tiny bank (+ MLflow)."""

from __future__ import annotations

import csv
import io
import os
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from aniformer.checkpoint import model_from_checkpoint, save_checkpoint
from aniformer.cli.exits import run
from aniformer.errors import UserError
from aniformer.evaluate import (
    Contender,
    Samplers,
    acceleration_error,
    clip_accelerations,
    copy_driver_contender,
    evaluate_table,
    noise_sweep,
    parse_levels,
    split_pmd,
    static_target_contender,
)
from aniformer.geometry import center_bbox
from aniformer.io.report import ratio_rows, table_csv, table_markdown
from aniformer.model import AniFormer, AniFormerConfig
from aniformer.models import NPT, NPTConfig

ROOT = Path(__file__).resolve().parents[1]
TINY_DATA = yaml.safe_load((ROOT / "configs" / "tiny.yaml").read_text())["data"]
TINY_MODEL = dict(channels=(16,), extractor_channels=(8, 16), heads=2, window=3)


def save(path: Path, name: str, model) -> Path:
    optimizer = torch.optim.Adam(model.parameters())
    scheduler = torch.optim.lr_scheduler.MultiStepLR(optimizer, [1])
    config = {"data": TINY_DATA, "model": {"name": name, **model.config.to_dict()}}
    return save_checkpoint(path, config=config, model=model, optimizer=optimizer, scheduler=scheduler, epoch=1, step=1)


# --------------------------------------------------------------------------------------------
# Pure parts, on a fake sampler
# --------------------------------------------------------------------------------------------


class FakeSampler:
    """Pairs whose ground truth is the driver moved by +1 cm in x (and shuffled like the pipeline when asked)."""

    def __init__(self, window: int, shuffle: str):
        self.window, self.shuffle = window, shuffle

    def batch(self, split, epoch, indices, n=None):
        rng = np.random.default_rng(len(split))
        B, V = len(indices), 20
        driving = center_bbox(rng.normal(size=(B, self.window, V, 3)).astype(np.float32))
        gt = driving + np.float32([0.01, 0, 0])
        if self.shuffle != "none":
            gt = gt[:, :, rng.permutation(V)]
        return {"driving": driving, "target": driving[:, 0], "ground_truth": gt}


def test_copy_driver_pmd_is_known_and_uses_unshuffled_pairs():
    samplers = Samplers(FakeSampler, shuffle="target")
    table = evaluate_table([copy_driver_contender(3)], samplers, ["seen", "unseen"], pairs=10, batch_size=4)
    # |(0.01, 0, 0)|^2 = 1e-4 m^2 -> 1.0 in units of 1e-4
    assert table["copy-driver"]["seen"] == pytest.approx(1.0, rel=1e-4)
    assert set(samplers._cache) == {(3, "none")}


def test_frames_slice_and_noise_are_deterministic():
    centre_only = Contender("centre", lambda d, t, f: d[:, 1:2] + torch.tensor([0.02, 0, 0]), 3, slice(1, 2))
    sampler = FakeSampler(3, "none")
    assert split_pmd(centre_only, sampler, "seen", pairs=6) == pytest.approx(1.0, rel=1e-4)  # (2-1 cm)^2
    a = split_pmd(copy_driver_contender(3), sampler, "seen", pairs=6, noise=0.01, seed=1)
    b = split_pmd(copy_driver_contender(3), sampler, "seen", pairs=6, noise=0.01, seed=1)
    c = split_pmd(copy_driver_contender(3), sampler, "seen", pairs=6, noise=0.01, seed=2)
    assert a == b != c and a > 1.0
    sweep = noise_sweep([copy_driver_contender(3)], Samplers(FakeSampler, "none"), "seen", [0.0, 0.02], pairs=6)
    assert sweep["copy-driver"][0.0] < sweep["copy-driver"][0.02]


def test_parse_levels_and_reports():
    assert parse_levels("0.01, 0,0.005") == [0.0, 0.005, 0.01]
    for bad in ("a", "-1", "nan", ""):
        with pytest.raises(ValueError):
            parse_levels(bad)
    table = {"AniFormer": {"seen": 0.5, "unseen": 2.0}, "copy-driver": {"seen": 1.0, "unseen": 1.5}}
    md = table_markdown(table, ["seen", "unseen"], {"seen": "seen motions"})
    assert "| AniFormer | **0.50** | 2.00 |" in md and "| copy-driver | 1.00 | **1.50** |" in md
    assert "`seen`: seen motions" in md
    rows = list(csv.reader(io.StringIO(table_csv(table, ["seen", "unseen"]))))
    assert rows == [["method", "seen", "unseen"], ["AniFormer", "0.5", "2"], ["copy-driver", "1", "1.5"]]


def test_ratio_rows_divide_each_model_by_the_transfer_and_the_better_trivial_baseline():
    table = {"A": {"seen": 6.0}, "B": {"seen": 1.0}, "copy-driver": {"seen": 30.0}, "static target": {"seen": 20.0},
             "deformation transfer": {"seen": 12.0}}
    assert ratio_rows(table) == {"A ÷ transfer": {"seen": 0.5}, "B ÷ transfer": {"seen": 1 / 12},
                                 "A ÷ min(copy-driver, static target)": {"seen": 0.3},
                                 "B ÷ min(copy-driver, static target)": {"seen": 0.05}}
    md = table_markdown(table, ["seen"], ratios=True)
    assert "| **B** | **1.00** |" not in md and "| B | **1.00** |" in md  # a ratio is never the column's best
    assert "| A ÷ transfer | 0.50 |" in md and "| B ÷ min(copy-driver, static target) | 0.05 |" in md
    assert ratio_rows({"A": {"seen": 1.0}}) == {}  # no baseline rows, no ratios
    # the skinned transfer: a reference for the models, and divided by the others itself
    ratios = ratio_rows(table | {"skinned transfer": {"seen": 3.0}})
    assert ratios["A ÷ skinned transfer"] == {"seen": 2.0} and ratios["skinned transfer ÷ transfer"] == {"seen": 0.25}
    assert "skinned transfer ÷ skinned transfer" not in ratios


def test_acceleration_error_is_the_mean_distance_of_second_differences():
    truth = torch.randn(2, 6, 5, 3)
    moved = truth + torch.tensor([0.1, -0.2, 0.3])  # a constant offset moves no vertex's acceleration
    assert torch.allclose(acceleration_error(moved, truth), torch.zeros(2), atol=1e-6)
    bumped = truth.clone()
    bumped[:, 3, :, 0] += 0.01  # one frame off by 1 cm in x: accelerations at frames 2, 3, 4 off by 1, 2, 1 cm
    assert torch.allclose(acceleration_error(bumped, truth), torch.full((2,), (0.01 + 0.02 + 0.01) / 4), atol=1e-6)


def test_clip_accelerations_slide_each_window_over_the_clip():
    """Per clip, in mm/frame², recomputed here: the static target's error is the clip's own mean vertex
    acceleration, and the copy-driver's the driver's accelerations against the truth's."""
    from aniformer.synth.stream import StreamPairs

    clips = StreamPairs("notoes_collapse3pc", window=8, eval_pairs=2)
    batch = clips.batch("seen", 0, np.arange(2), n=2)
    scores = clip_accelerations([copy_driver_contender(3), static_target_contender(3)], clips, "seen", pairs=2)
    truth = np.asarray(batch["ground_truth"], np.float64)
    own = np.linalg.norm(truth[:, 2:] - 2 * truth[:, 1:-1] + truth[:, :-2], axis=-1).mean((1, 2)) * 1000
    assert scores["static target"] == pytest.approx(own, rel=1e-4)
    driving = np.asarray(batch["driving"], np.float64)
    copied = np.linalg.norm((driving[:, 2:] - 2 * driving[:, 1:-1] + driving[:, :-2])
                            - (truth[:, 2:] - 2 * truth[:, 1:-1] + truth[:, :-2]), axis=-1).mean((1, 2)) * 1000
    assert scores["copy-driver"] == pytest.approx(copied, rel=1e-4)
    assert (scores["copy-driver"] < scores["static target"]).all()


# --------------------------------------------------------------------------------------------
# jobs/evaluate.py on the tiny bank
# --------------------------------------------------------------------------------------------


def evaluate_main(argv):
    from jobs.evaluate import main

    return main([str(a) for a in argv])


@pytest.fixture(scope="module")
def tiny_run(ray_cluster, tmp_path_factory) -> Path:
    """A run directory as jobs/train.py leaves it: bank/ and best.pt (untrained tiny models), plus baselines."""
    from pipeline import data

    root = tmp_path_factory.mktemp("eval")
    data.generate_bank(data.data_config({"data": TINY_DATA}), root / "bank", workers=2, progress=False)
    torch.manual_seed(0)
    save(root / "best.pt", "aniformer", AniFormer(AniFormerConfig(**TINY_MODEL)))
    save(root / "npt.pt", "npt", NPT(NPTConfig(extractor_channels=(8, 16), channels=(19, 16), window=3)))
    save(root / "regression.pt", "aniformer", AniFormer(AniFormerConfig(**TINY_MODEL, head="regression")))
    return root


@pytest.mark.slow
@pytest.mark.ray
def test_evaluate_job_end_to_end_with_mlflow(tiny_run, tmp_path, monkeypatch, capsys, scoring):
    import mlflow
    from mlflow.tracking import MlflowClient

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    client = MlflowClient(uri)
    # The checkpoint as a training run logs it: artifact checkpoints/best.pt of an MLflow run.
    exp = client.create_experiment("training", artifact_location=(tmp_path / "artifacts").as_uri())
    train_run = client.create_run(exp).info.run_id
    client.log_artifact(train_run, str(tiny_run / "best.pt"), "checkpoints")

    out = tmp_path / "eval"
    evaluate_main(["--checkpoint", train_run, "--bank", tiny_run / "bank", "--out", out, "--name", "tiny",
                   "--compare", f"NPT={tiny_run / 'npt.pt'}", "--compare", f"regression head={tiny_run / 'regression.pt'}",
                   "--pairs", 4, "--noise", "0,0.01,0.02", "--no-progress"])
    printed = capsys.readouterr().out
    splits = ["train", "seen", "unseen", "unseen_drivers", "heldout_actions"]
    rows = list(csv.DictReader((out / "results.csv").open()))
    assert [r["method"] for r in rows] == ["tiny", "NPT", "regression head", "copy-driver", "static target",
                                           "deformation transfer"]
    assert list(rows[0]) == ["method", *splits]
    # each row is its predictor's PMD on the same 4 pairs (the checkpoint's seed), recomputed here from the bank
    from pipeline.data import PairSampler, load_bank

    bank = load_bank(tiny_run / "bank")

    def sampler(shuffle: str) -> PairSampler:
        return PairSampler(bank, window=3, shuffle=shuffle, center=TINY_DATA["center"], seed=TINY_DATA["seed"],
                           eval_pairs=4)

    model, _ = model_from_checkpoint(tiny_run / "best.pt")
    table = {r["method"]: r for r in rows}
    for split in splits:
        assert float(table["copy-driver"][split]) == pytest.approx(scoring.pmd(sampler("none"), split, 4), rel=1e-4)
        assert float(table["static target"][split]) == pytest.approx(
            scoring.pmd(sampler("none"), split, 4, scoring.static_target), rel=1e-4)
        assert float(table["tiny"][split]) == pytest.approx(scoring.pmd(
            sampler(TINY_DATA["shuffle"]), split, 4, scoring.model_predict(model), model.config.output_frames()), rel=1e-4)
    md = (out / "results.md").read_text()
    for name in ("tiny", "NPT", "regression head", "copy-driver", "static target", "deformation transfer"):
        assert f"| {name} |" in md
    assert "| method | " + " | ".join(splits) + " |" in md and "noise.png" in md
    noise_rows = list(csv.DictReader((out / "noise.csv").open()))
    methods = [r["method"] for r in rows]
    assert [(r["method"], r["noise_m"]) for r in noise_rows] == [(m, level) for m in methods for level in ("0", "0.01", "0.02")]
    noise = {(r["method"], float(r["noise_m"])): float(r["pmd_x1e4"]) for r in noise_rows}
    for method, row in zip(methods, rows):  # the sweep's own pass over the pairs: at no noise, the table's PMD
        assert noise[(method, 0.0)] == pytest.approx(float(row["unseen"]), rel=1e-4), method
    # the static target never looks at the driver, so driver noise cannot change its PMD; copying the
    # noisy driver gets worse with more noise
    assert noise[("static target", 0.01)] == noise[("static target", 0.02)] == noise[("static target", 0.0)]
    assert noise[("copy-driver", 0.0)] < noise[("copy-driver", 0.01)] < noise[("copy-driver", 0.02)]
    from PIL import Image

    with Image.open(out / "noise.png") as plot:  # the plot as plot_sweep draws it: 5 x 3.5 in at 120 dpi
        assert plot.format == "PNG" and plot.size == (600, 420)
        colours = plot.convert("RGB").getcolors(maxcolors=1 << 20)
    assert len(colours) > 50, "a blank plot"  # six coloured lines, their markers, text, anti-aliasing
    assert "results.md" in printed and "MLflow run" in printed

    (run,) = mlflow.search_runs(experiment_names=["aniformer"], output_format="list")
    assert run.info.run_name == "evaluate-tiny" and run.info.status == "FINISHED"
    assert run.data.metrics["pmd_seen.copy-driver"] == pytest.approx(float(rows[3]["seen"]), rel=1e-4)
    assert run.data.tags["aniformer.source_run"] == train_run
    artifacts = {a.path for a in client.list_artifacts(run.info.run_id, "evaluation")}
    assert {"evaluation/results.md", "evaluation/results.csv", "evaluation/noise.png"} <= artifacts
    assert sorted(p.name for p in tmp_path.iterdir()) == ["artifacts", "eval", "mlartifacts", "mlflow.db"]


@pytest.mark.slow
@pytest.mark.ray
def test_evaluate_default_bank_beside_checkpoint_matches_training_metric(tiny_run, tmp_path):
    """No --bank: bank/ beside best.pt; PMD over the same pairs as pipeline.train's evaluation."""
    from aniformer.metrics import PMD_SCALE, pmd
    from pipeline.data import PairSampler

    out = tmp_path / "e"
    evaluate_main(["--checkpoint", tiny_run / "best.pt", "--out", out, "--splits", "unseen", "--pairs", 5,
                   "--no-mlflow", "--no-progress", "--no-copy-driver"])
    rows = list(csv.DictReader((out / "results.csv").open()))
    assert [r["method"] for r in rows] == ["AniFormer"]
    model, _ = model_from_checkpoint(tiny_run / "best.pt")
    sampler = PairSampler.from_dir(tiny_run / "bank")
    with torch.no_grad():
        batch = sampler.batch("unseen", 0, np.arange(5), n=5)
        expected = pmd(model(torch.from_numpy(batch["driving"]), torch.from_numpy(batch["target"])),
                       torch.from_numpy(batch["ground_truth"])).item() * PMD_SCALE
    assert float(rows[0]["unseen"]) == pytest.approx(expected, rel=1e-4)


@pytest.mark.slow
@pytest.mark.ray
def test_evaluate_skinned_transfer_row_is_its_pmd_on_the_unshuffled_pairs(tiny_run, tmp_path):
    """--skinned-transfer: a row of its own, scored on the pairs in correspondence, and each model's ratio to it."""
    from aniformer.metrics import PMD_SCALE, pmd
    from aniformer.skinned_transfer import skinned_transfer
    from pipeline.data import PairSampler, load_bank

    out = tmp_path / "e"
    evaluate_main(["--checkpoint", tiny_run / "best.pt", "--out", out, "--splits", "unseen", "--pairs", 4,
                   "--no-mlflow", "--no-progress", "--no-copy-driver", "--skinned-transfer"])
    rows = {r["method"]: r for r in csv.DictReader((out / "results.csv").open())}
    assert list(rows) == ["AniFormer", "skinned transfer"]
    sampler = PairSampler(load_bank(tiny_run / "bank"), window=3, shuffle="none", center=TINY_DATA["center"],
                          seed=TINY_DATA["seed"], eval_pairs=4)
    batch = {k: torch.from_numpy(v) for k, v in sampler.batch("unseen", 0, np.arange(4), n=4).items()}
    expected = pmd(skinned_transfer(batch["driving"], batch["target"], batch["target_faces"]),
                   batch["ground_truth"]).item() * PMD_SCALE
    assert float(rows["skinned transfer"]["unseen"]) == pytest.approx(expected, rel=1e-4)
    assert "| AniFormer ÷ skinned transfer |" in (out / "results.md").read_text()


def _bad_eval(kind: str, root: Path, run_dir: Path) -> tuple[list, str]:
    base = ["--checkpoint", run_dir / "best.pt", "--out", root / "out", "--no-mlflow", "--no-progress", "--pairs", 2]
    if kind == "missing checkpoint":
        base[1] = root / "none.pt"
        return base, "checkpoint not found"
    if kind == "garbage checkpoint":
        (root / "bad.pt").write_bytes(os.urandom(100))
        base[1] = root / "bad.pt"
        return base, "not a readable checkpoint"
    if kind == "config mismatch":
        state = torch.load(run_dir / "best.pt", weights_only=True)
        state["config"]["model"]["channels"] = [32, 32]  # a valid config, of other shapes than the weights
        torch.save(state, root / "m.pt")
        base[1] = root / "m.pt"
        return base, "does not match"
    if kind == "no bank beside":
        import shutil

        shutil.copy(run_dir / "best.pt", root / "lonely.pt")
        base[1] = root / "lonely.pt"
        return base, "pass --bank"
    if kind == "bank not a bank":
        (root / "nobank").mkdir()
        return base + ["--bank", root / "nobank"], "not a mesh bank"
    if kind == "unknown split":
        return base + ["--splits", "seen,bogus"], "unknown split(s) bogus"
    if kind == "bad noise":
        return base + ["--noise", "0,-1"], "--noise"
    if kind == "bad compare":
        return base + ["--compare", "npt"], "NAME=CKPT"
    if kind == "compare missing":
        return base + ["--compare", f"npt={root / 'x.pt'}"], "checkpoint not found"
    if kind == "duplicate names":
        return base + ["--compare", f"copy-driver={run_dir / 'npt.pt'}"], "unique"
    if kind == "bad pairs":
        return base[:-2] + ["--pairs", 0], "--pairs"
    if kind == "unknown run id":
        base[1] = "0" * 32  # looks like a run id; no such run
        return base, "MLflow run 00000000"
    raise AssertionError(kind)


EVAL_BAD = ["missing checkpoint", "garbage checkpoint", "config mismatch", "no bank beside", "bank not a bank",
            "unknown split", "bad noise", "bad compare", "compare missing", "duplicate names", "bad pairs",
            "unknown run id"]


@pytest.mark.ray
@pytest.mark.parametrize("kind", EVAL_BAD)
def test_evaluate_bad_input_is_one_line(kind, tiny_run, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    argv, word = _bad_eval(kind, tmp_path, tiny_run)
    before = set(tmp_path.iterdir())
    with pytest.raises(SystemExit) as exc:
        run(evaluate_main, [str(a) for a in argv])
    assert exc.value.code == 2
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1 and word in lines[0], lines
    assert not (tmp_path / "out").exists()
    assert {p for p in set(tmp_path.iterdir()) - before if not p.name.startswith("mlflow")} == set()


def test_evaluate_user_errors_before_any_work(tmp_path):
    with pytest.raises(UserError, match="--batch-size"):
        evaluate_main(["--checkpoint", "x", "--out", tmp_path, "--batch-size", "0"])
    with pytest.raises(UserError, match="required"):
        evaluate_main(["--out", tmp_path])


@pytest.mark.slow
@pytest.mark.ray
def test_export_then_animate_is_the_documented_flow(tiny_run, tmp_path, capsys):
    """jobs/export_meshes.py turns a bank split into OBJ inputs that jobs/animate.py takes as they are."""
    from aniformer.animate import driving_files, load_driving
    from aniformer.errors import UserError
    from aniformer.io.glb import read_glb
    from aniformer.io.mesh import load_mesh
    from jobs.animate import main as animate_main
    from jobs.export_meshes import main as export_main
    from pipeline.data import load_bank

    samples = tmp_path / "samples"
    export_main(["--bank", str(tiny_run / "bank"), "--split", "unseen", "--out", str(samples)])
    bank = load_bank(tiny_run / "bank")
    split = bank.manifest.splits["unseen"]
    motion, target = split["motions"][0], split["targets"][0]
    driving, faces = load_driving(driving_files(str(samples / "driving")))
    truth, _ = load_driving(driving_files(str(samples / "ground_truth")))
    np.testing.assert_allclose(driving, bank.sequence(bank.manifest.motions[motion]["driver"], motion), atol=1e-6)
    np.testing.assert_allclose(truth, bank.sequence(target, motion), atol=1e-6)
    np.testing.assert_array_equal(faces, bank.faces)
    assert load_mesh(samples / "target.obj")[0].shape == (bank.num_vertices, 3)
    with pytest.raises(UserError, match="not in split"):
        export_main(["--bank", str(tiny_run / "bank"), "--split", "unseen", "--motion", "-1", "--out", str(tmp_path / "x")])
    assert not (tmp_path / "x").exists()

    anim = tmp_path / "anim"
    animate_main(["--checkpoint", str(tiny_run / "best.pt"), "--target", str(samples / "target.obj"), "--driving",
                  str(samples / "driving"), "--out", str(anim), "--no-progress", "--device", "cpu", "--preview-frames", "4",
                  "--force"])  # two epochs of training: the self-check may refuse its result
    assert len(list((anim / "frames").glob("frame_*.obj"))) == len(driving)
    assert read_glb(anim / "animation.glb")["frames"].shape == (len(driving), bank.num_vertices, 3)
    assert "exported" in capsys.readouterr().out
