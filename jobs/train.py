"""Train AniFormer (or a baseline) with Ray Train, tracked in MLflow.

    python jobs/train.py --config configs/default.yaml --out runs/default [train.epochs=20 ...]
    ray job submit --working-dir . -- python jobs/train.py --config configs/tiny.yaml --out /abs/runs/tiny

Without RAY_ADDRESS a local Ray instance is started (dashboard on 127.0.0.1 only); with it, or under
`ray job submit`, the job runs on that cluster. The mesh bank is `--bank DIR` if given, else
`OUT/bank`, generated there on first use. Running the same command again (same `--out` and job name)
resumes from the latest checkpoint (the newest intact one) and continues the same MLflow run, which is
identified by the absolute `--out` and the name. One job at a time per `--out`: it is locked (`OUT/.lock`)
and a second job is refused, naming the first. Outputs: `OUT/best.pt`,
`OUT/last.pt`, Ray's checkpoints under `OUT/ray/NAME`, and the MLflow run (printed at the end), which
holds `OUT/best.pt` as an MLflow model registered as a new version of `aniformer` (`--register-as
NAME`; `--no-register` logs it to the run only): `jobs/animate.py --checkpoint models:/aniformer/latest`
and `mlflow.pyfunc.load_model("models:/aniformer/latest")` load it (pipeline/registry.py).
"""

from __future__ import annotations

from aniformer.cli.args import RunJobParser, load_config
from aniformer.cli.exits import exit_on_sigterm, run
from aniformer.cli.locks import releases_locks


@releases_locks  # the --out lock ends with main, however main is called
def main(argv: list[str]) -> None:
    parser = RunJobParser("train.py", __doc__, out_help="output directory (checkpoints, bank)",
                          name_help="job name: MLflow run and Ray run")
    parser.add_argument("--no-progress", action="store_true",
                        help="no progress bar (it is shown only when stderr is a terminal anyway)")
    parser.add_argument("--verbose", action="store_true", help="Ray's own INFO logs (Ray Data, Ray Train)")
    parser.add_argument("--register-as", default="aniformer", metavar="NAME",
                        help="registered MLflow model the best checkpoint becomes a new version of (default: aniformer)")
    parser.add_argument("--no-register", action="store_true",
                        help="log the best checkpoint as an MLflow model of the run, but register no version")
    args = parser.parse_args(argv)
    config = load_config(args.config, args.overrides)
    from pipeline.registry import check_registered_name
    from pipeline.run_spec import RunSpec

    spec = RunSpec.from_config(config)  # bad config: one line before anything starts
    register_as = None if args.no_register else check_registered_name(args.register_as)
    out, name, bank = RunJobParser.locations(args)

    from pipeline.cluster import connect
    from pipeline.console import Console, quiet_ray
    from pipeline.data import prepare_bank
    from pipeline.registry import log_best_model
    from pipeline.tracking import quiet_mlflow, start_job_run, ui_hint
    from pipeline.trainer import train_job

    quiet_mlflow()
    console = Console.for_job(no_progress=args.no_progress, verbose=args.verbose)
    quiet_ray(console.verbose)
    dashboard = connect()
    exit_on_sigterm()  # after ray.init, which installs its own handler
    _, faces = prepare_bank(spec.data, bank, generate=args.bank is None)
    tracker = start_job_run(name, spec.to_dict(), experiment=args.experiment, out=out)
    pairs = "made on the fly (data.source: stream)" if spec.data.source == "stream" else f"from the bank {bank}"
    print(f"run {name}: pairs {pairs}; checkpoints in {out} (best.pt, last.pt; Ray's in {out / 'ray'}); "
          f"MLflow run {tracker.run_id} in {tracker.uri}" + (f"; Ray dashboard http://{dashboard}" if dashboard else ""),
          flush=True)
    # `ray job stop` and kill send SIGTERM: `run` makes it exit 143, the run ends KILLED (never RUNNING).
    with tracker.ended():
        result = train_job(spec, bank, out, name, tracker, faces, console)
        model_uri = log_best_model(tracker, out / "best.pt", register_as)
    metrics = result.metrics or {}
    print(f"trained {name}: epoch {metrics.get('epoch')}, PMD seen {metrics.get('pmd_seen', float('nan')):.3f}, "
          f"unseen {metrics.get('pmd_unseen', float('nan')):.3f} (x1e-4)")
    print(f"checkpoints: {out / 'best.pt'} (best unseen PMD), {out / 'last.pt'}")
    print(f"MLflow run: {tracker.run_id} in {tracker.uri}")
    print(f"  best model: {model_uri} (jobs/animate.py --checkpoint {model_uri}, or mlflow.pyfunc.load_model)")
    print(f"  compare runs: {ui_hint(tracker.uri)}")


def cli() -> None:
    """The ``aniformer-train`` command: `main` with one-line errors and exit codes."""
    run(main)


if __name__ == "__main__":
    cli()
