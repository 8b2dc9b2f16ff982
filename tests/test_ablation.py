"""Ablations (pipeline/ablation.py, jobs/ablate.py): config parsing and a tiny run end to end."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from aniformer.errors import UserError

ROOT = Path(__file__).resolve().parents[1]


def write_config(path: Path, ablation: dict, base: str | None = str(ROOT / "configs/tiny.yaml"), **sections) -> Path:
    config = {"ablation": ablation, **sections}
    if base is not None:
        config["base"] = base
    path.write_text(yaml.safe_dump(config))
    return path


def test_shipped_ablation_config_has_the_paper_rows_and_one_budget():
    from pipeline.ablation import load_ablation_config, variant_specs

    base, ablation = load_ablation_config(ROOT / "configs/ablation.yaml")
    specs = variant_specs(base, ablation)
    full = specs["AniFormer (full)"]
    default = yaml.safe_load((ROOT / "configs/bank.yaml").read_text())
    assert full.train.epochs == default["train"]["epochs"] and full.model.channels == tuple(default["model"]["channels"])
    assert specs["regression head"].model.head == "regression"
    assert (specs["no head"].loss.motion, specs["no head"].loss.appearance) == (0, 0)
    assert specs["+ L_m"].loss.motion > 0 == specs["+ L_m"].loss.appearance
    assert specs["+ L_a"].loss.appearance > 0 == specs["+ L_a"].loss.motion
    assert specs["NPT (frame by frame)"].model_name == "npt"
    assert {s.train.epochs for s in specs.values()} == {full.train.epochs}
    # the paper's per-frame embedding everywhere but in our switch's row; the full row is the default config
    assert full.model.temporal == "embedding" == specs["no head"].model.temporal
    assert specs["temporal attention"].model.temporal == "attention"
    from pipeline.run_spec import RunSpec
    assert full.to_dict() == RunSpec.from_config(default).to_dict()


def test_shipped_seeds_config_repeats_the_default_and_varies_only_the_seed():
    from pipeline.ablation import load_ablation_config, variant_specs
    from pipeline.run_spec import RunSpec

    specs = variant_specs(*load_ablation_config(ROOT / "configs/seeds.yaml"))
    default = RunSpec.from_config(yaml.safe_load((ROOT / "configs/bank.yaml").read_text())).to_dict()
    assert specs["paper design s0"].to_dict() == default
    for design in ("paper design", "temporal attention", "NPT"):
        runs = [specs[f"{design} s{seed}"].to_dict() for seed in range(5)]
        assert [r["train"]["seed"] for r in runs] == list(range(5))
        assert all({**r, "train": {**r["train"], "seed": 0}} == runs[0] for r in runs)
    assert specs["paper design s0"].model.temporal == "embedding" and specs["NPT s0"].model_name == "npt"


def test_shipped_head_dim_config_varies_only_the_heads_and_the_seed():
    from pipeline.ablation import load_ablation_config, variant_specs

    specs = variant_specs(*load_ablation_config(ROOT / "configs/head_dim.yaml"))
    assert {name: spec.model.stage_heads() for name, spec in specs.items()} == {
        **{f"2 heads s{seed}": (2, 2) for seed in range(3)}, **{f"head dim 32 s{seed}": (2, 1) for seed in range(3)}}
    base = specs["2 heads s0"].to_dict()
    for name, spec in specs.items():
        run = spec.to_dict()
        assert {**run, "model": {**run["model"], "heads": 2}, "train": {**run["train"], "seed": 0}} == base, name


def test_bad_ablation_configs_fail_with_one_line(tmp_path):
    from pipeline.ablation import load_ablation_config, variant_specs

    def fails(path: Path, message: str, overrides=()):
        with pytest.raises(UserError, match=message):
            base, ablation = load_ablation_config(path, overrides)
            variant_specs(base, ablation)

    fails(write_config(tmp_path / "a.yaml", {"variants": {"long": ["train.epochs=50"]}}), "changes the budget")
    fails(write_config(tmp_path / "b.yaml", {"variants": {"x": ["model.attention=sideways"]}}), "variant 'x'.*attention")
    fails(write_config(tmp_path / "c.yaml", {"variants": {"a b": [], "a-b": []}}), "differ in their letters")
    fails(write_config(tmp_path / "d.yaml", {"variants": {}}), "variants must map")
    fails(write_config(tmp_path / "e.yaml", {"variants": {"x": []}}, train={"epochs": 3}), "base: .* and run sections")
    fails(write_config(tmp_path / "f.yaml", {"variants": {"x": []}}), "unknown key", ["ablation.depth=3"])
    fails(write_config(tmp_path / "h.yaml", {"common": [3], "variants": {"x": []}}), "common must be")
    # overrides on the command line apply to the base config, variants on top
    base, ablation = load_ablation_config(write_config(tmp_path / "g.yaml", {
        "common": ["train.lr=0.1", "model.heads=2"], "variants": {"x": ["train.lr=0.5"]}}), ["train.epochs=1"])
    (spec,) = variant_specs(base, ablation).values()
    assert (spec.train.epochs, spec.train.lr, spec.model.heads) == (1, 0.5, 2)


def test_pmd_table_is_an_mlflow_table_replaced_when_logged_again(tmp_path, monkeypatch):
    """log_pmd_table: what `mlflow.load_table` reads and the UI's artifact view shows as a table; a
    resumed job logging it again replaces it (MlflowClient.log_table would append the rows)."""
    from pipeline.ablation import log_pmd_table
    from pipeline.tracking import start_job_run

    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    tracker = start_job_run("abl", {})
    table = {"AniFormer (full)": {"seen": 12.5, "unseen": 14.25}, "copy-driver": {"seen": 40.0, "unseen": 41.0}}
    log_pmd_table(tracker, table, ["seen", "unseen"], notes={"AniFormer (full)": "(base config)"})
    table["AniFormer (full)"]["unseen"] = 13.0
    path = log_pmd_table(tracker, table, ["seen", "unseen"], notes={"AniFormer (full)": "(base config)"})
    experiment = tracker.client.get_run(tracker.run_id).info.experiment_id
    loaded = tracker.client.load_table(experiment, path, run_ids=[tracker.run_id])
    assert list(loaded.columns) == ["method", "seen", "unseen", "about"]
    assert loaded.to_dict("records") == [
        {"method": "AniFormer (full)", "seen": 12.5, "unseen": 13.0, "about": "(base config)"},
        {"method": "copy-driver", "seen": 40.0, "unseen": 41.0, "about": ""}]
    tags = tracker.client.get_run(tracker.run_id).data.tags
    assert json.loads(tags["mlflow.loggedArtifacts"]) == [{"path": "ablation/pmd_table.json", "type": "table"}]
    with pytest.raises(ValueError, match=".json"):
        log_pmd_table(tracker, table, ["seen"], artifact_file="ablation/pmd.csv")


@pytest.mark.slow
@pytest.mark.ray
def test_ablation_job_trains_every_variant_then_one_table(tmp_path, ray_address, scoring):
    from mlflow.tracking import MlflowClient

    config = write_config(tmp_path / "ablation.yaml", {
        "pairs": 16,
        "variants": {"AniFormer (full)": [], "cross, shuffle both": ["model.attention=cross", "data.shuffle=both"]}})
    out = tmp_path / "abl"
    env = {**os.environ, "RAY_ADDRESS": ray_address, "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}"}
    cmd = [sys.executable, str(ROOT / "jobs/ablate.py"), "--config", str(config), "--out", str(out), "train.epochs=1"]
    first = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=900, cwd=tmp_path)
    assert first.returncode == 0, first.stdout[-3000:] + first.stderr[-3000:]

    with open(out / "ablation.csv") as f:
        rows = {r["method"]: r for r in csv.DictReader(f)}
    assert set(rows) == {"AniFormer (full)", "cross, shuffle both", "copy-driver", "static target",
                         "deformation transfer"}
    splits = json.loads((out / "ablation.json").read_text())["splits"]
    assert {"seen", "unseen"} <= set(splits)
    from aniformer.checkpoint import load_checkpoint, model_from_checkpoint
    from aniformer.cli.args import load_config
    from pipeline.ablation import slug
    from pipeline.data import PairSampler, load_bank
    from pipeline.run_spec import RunSpec

    tiny = RunSpec.from_config(load_config(ROOT / "configs/tiny.yaml"))
    # Every row is the PMD of its own predictor on the same 16 pairs, recomputed here from the bank.
    bank = load_bank(out / "bank")

    def sampler(shuffle: str) -> PairSampler:
        return PairSampler(bank, window=tiny.data.window, shuffle=shuffle, center=tiny.data.center,
                           seed=tiny.data.seed, eval_pairs=16)

    models = {row: (model_from_checkpoint(out / "runs" / slug(row) / "best.pt")[0], shuffle)
              for row, shuffle in {"AniFormer (full)": tiny.data.shuffle, "cross, shuffle both": "both"}.items()}
    for split in splits:
        assert float(rows["copy-driver"][split]) == pytest.approx(scoring.pmd(sampler("none"), split, 16), rel=1e-4)
        assert float(rows["static target"][split]) == pytest.approx(
            scoring.pmd(sampler("none"), split, 16, scoring.static_target), rel=1e-4)
        for row, (model, shuffle) in models.items():
            assert float(rows[row][split]) == pytest.approx(scoring.pmd(
                sampler(shuffle), split, 16, scoring.model_predict(model), model.config.output_frames()), rel=1e-4), (row, split)
    # each variant's checkpoint was trained (1 epoch) with that variant's overrides, the base with none
    for variant, trained_with in {"aniformer_full": (tiny.model.attention, tiny.data.shuffle),
                                  "cross_shuffle_both": ("cross", "both")}.items():
        state = load_checkpoint(out / "runs" / variant / "best.pt")
        assert (state["epoch"], state["config"]["model"]["attention"], state["config"]["data"]["shuffle"]) == (
            1, *trained_with), variant
    markdown = (out / "ablation.md").read_text()
    assert "| AniFormer (full) |" in markdown and "| cross, shuffle both ÷ transfer |" in markdown
    assert json.loads((out / "ablation.json").read_text())["acceleration"] is None  # a bank: no clips to animate

    client = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
    runs = client.search_runs([client.get_experiment_by_name("aniformer").experiment_id])
    (parent,) = [r for r in runs if r.data.tags.get("kind") == "ablation"]
    children = [r for r in runs if r.data.tags.get("mlflow.parentRunId") == parent.info.run_id]
    assert parent.info.status == "FINISHED" and len(children) == 2
    assert all(c.info.status == "FINISHED" and client.get_metric_history(c.info.run_id, "pmd_unseen") for c in children)
    assert parent.data.metrics["pmd_unseen.cross_shuffle_both"] == pytest.approx(
        float(rows["cross, shuffle both"]["unseen"]), rel=1e-4)

    # Again: every variant is kept, nothing retrains, the same table comes out.
    second = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert second.returncode == 0, second.stdout[-3000:] + second.stderr[-3000:]
    assert second.stdout.count("kept:") == 2 and "training (" not in second.stdout
    with open(out / "ablation.csv") as f:
        assert {r["method"]: r for r in csv.DictReader(f)} == rows
