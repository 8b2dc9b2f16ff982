"""Sweep the loss weights and the window length with Ray Tune under a per-worker memory limit.

    python jobs/sweep.py --config configs/sweep_tiny.yaml --out runs/sweep_tiny [sweep.num_samples=8 ...]
    mlflow ui --backend-store-uri sqlite:///mlflow.db      # compare the trials (children of the sweep run)

The config is a run config (data/model/loss/train, as for jobs/train.py) plus a `sweep:` section
(see pipeline/tune.py `SweepConfig`). Trials predicted over `sweep.memory_limit_gb` run with a
smaller batch and gradient accumulation, or are skipped, before anything is built. Outputs:
`OUT/summary.csv` (one row per trial), the Tune experiment under `OUT/tune/NAME`, each trial's
checkpoints under `OUT/trials/`, and the MLflow runs (a parent per sweep, a child per trial).
Running the same command again after an interruption restores the sweep: finished trials are kept,
only the unfinished ones run. Without RAY_ADDRESS a local Ray instance is started.
"""

from __future__ import annotations

import sys

from aniformer.cli.args import RunJobParser, load_config
from aniformer.cli.exits import exit_on_sigterm, run
from aniformer.cli.locks import releases_locks


def report(name: str, rows: list, counts: dict, summary, best: dict | None, unfinished: list, parent) -> None:
    """The sweep's closing lines: trial counts, the summary file, the best trial, where to compare them."""
    from pipeline.sweep_table import compare_link
    from pipeline.tracking import ui_hint

    shown = ", ".join(f"{n} {k}" for k, n in sorted(counts.items()))
    print(f"sweep {name}: {len(rows)} trials ({shown})")
    print(f"summary: {summary}")
    if best and not unfinished:
        print(f"best trial {best['trial_id']}: PMD unseen {best['best_pmd_unseen']} (x1e-4), "
              f"rec={best['rec']:.3g} motion={best['motion']:.3g} appearance={best['appearance']:.3g} "
              f"window={best['window']}")
    print(f"MLflow parent run: {parent.run_id} in {parent.uri}")
    print(f"  compare trials: {ui_hint(parent.uri)}")
    link = compare_link(parent, rows)
    if link:
        print(f"  its trials side by side: {link}")
    if unfinished:
        print(f"interrupted: {len(unfinished)} trial(s) unfinished; run the same command again to resume",
              file=sys.stderr)


@releases_locks  # the --out lock ends with main, however main is called
def main(argv: list[str]) -> None:
    args = RunJobParser("sweep.py", __doc__, out_help="output directory (summary.csv, tune/, trials/)",
                        name_help="sweep name: MLflow parent run and Tune experiment").parse_args(argv)
    config = load_config(args.config, args.overrides)
    from pipeline.run_spec import RunSpec
    from pipeline.sweep_config import apply_params, split_config

    base, sweep = split_config(config)
    spec = RunSpec.from_config(base)  # bad config: one line before anything starts
    for window in sweep.window:  # both ends of the window range must make valid runs
        RunSpec.from_config(apply_params(base, {"window": window}))
    out, name, bank = RunJobParser.locations(args)

    from aniformer.synth.bodies import TOPOLOGIES
    from pipeline.cluster import connect
    from pipeline.data import pair_source, prepare_bank
    from pipeline.sweep_table import SweepReporter, best_row, record_results, summarize, write_summary
    from pipeline.tracking import start_job_run
    from pipeline.tune import build_tuner, end_interrupted_runs, experiment_exists, unfinished_trials

    connect()
    exit_on_sigterm()  # after ray.init, which installs its own handler
    manifest, faces = prepare_bank(spec.data, bank, generate=args.bank is None)
    largest = max(spec.data.train_topologies, key=TOPOLOGIES.get)  # the memory gate plans for its batches
    mesh_faces = faces if largest == spec.data.topology else pair_source(spec.data, bank, largest).faces
    vertices, face_count = int(manifest.num_vertices) if manifest else int(mesh_faces.max()) + 1, len(mesh_faces)
    restore = experiment_exists(out, name)
    parent = start_job_run(name, {**spec.to_dict(), "sweep": sweep.to_dict()}, experiment=args.experiment, out=out)
    parent.set_tags({"kind": "sweep", "sweep.search": sweep.search,
                     "memory_limit_gb": sweep.memory_limit_gb or "none"})
    status, unfinished = "FAILED", []
    try:
        print(("restoring" if restore else "starting") + f" sweep {name} in {out / 'tune' / name}", flush=True)
        tuner = build_tuner(base, sweep, sweep_name=name, out=out, bank=bank, experiment=args.experiment,
                            parent_run_id=parent.run_id, faces=faces, vertices=vertices, face_count=face_count,
                            restore=restore,
                            reporter=SweepReporter(base, sweep, sweep_name=name, epochs=spec.train.epochs,
                                                   vertices=vertices, faces=face_count))
        results = tuner.fit()
        unfinished = unfinished_trials(out / "tune" / name, sweep.num_samples)
        rows = summarize(results, sweep, spec.train.epochs)
        summary = write_summary(rows, out / "summary.csv")
        parent.log_artifact(summary)
        end_interrupted_runs(name, unfinished, args.experiment)
        best = best_row(rows)
        counts = record_results(parent, rows, best, complete=not unfinished)
        status = "KILLED" if unfinished else "FINISHED"
    except (KeyboardInterrupt, SystemExit):
        status = "KILLED"
        raise
    finally:
        parent.end(status)
    report(name, rows, counts, summary, best, unfinished, parent)
    if unfinished:
        sys.exit(1)


def cli() -> None:
    """The ``aniformer-sweep`` command: `main` with one-line errors and exit codes."""
    run(main)


if __name__ == "__main__":
    cli()
