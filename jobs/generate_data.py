"""Generate the synthetic mesh bank (or import folders of mesh sequences) as sharded Parquet.

    python jobs/generate_data.py --config configs/tiny.yaml --out data/tiny [data.seed=3 ...]
    python jobs/generate_data.py --config configs/default.yaml --out data/dfaust --from-meshes ~/dfaust_export

Overrides are ``key=value`` (dotted, values parsed as YAML); a bare key of the ``data:`` section
(``seed=3``) means ``data.seed=3``. Without ``RAY_ADDRESS`` a local Ray instance is started (no
dashboard; nothing listens beyond 127.0.0.1); with it, or under ``ray job submit``, the job runs on
that cluster (give ``--out`` as a path the driver can write, e.g. absolute, on shared storage).
Output is written under a temporary name beside ``--out`` and renamed into place when complete (a
killed job's is removed by the next one); an existing non-empty ``--out`` is refused unless
``--overwrite``, and so is an ``--out`` that is, holds or lies inside ``--from-meshes``. One job at a
time per ``--out``: a second is refused, naming the first.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

from aniformer.cli.args import ArgumentParser, load_config
from aniformer.cli.exits import exit_on_sigterm, run
from aniformer.cli.locks import releases_locks
from aniformer.cli.outputs import claim_output, staged_output_dir
from aniformer.errors import UserError


def parse_args(argv: list[str]) -> argparse.Namespace:
    p = ArgumentParser(prog="generate_data.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--config", required=True, metavar="FILE", help="YAML config with a data: section")
    p.add_argument("--out", required=True, metavar="DIR", help="bank directory to create")
    p.add_argument("--overwrite", action="store_true", help="replace an existing non-empty DIR")
    p.add_argument("--workers", type=int, default=None, help="generation actors (default: data.workers)")
    p.add_argument(
        "--from-meshes",
        metavar="SRC",
        default=None,
        help="import SRC/<identity>/<clip>/<frame meshes> instead of generating",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("overrides", nargs="*", metavar="key=value")
    return p.parse_args(argv)


def _normalise_overrides(overrides: list[str]) -> list[str]:
    from pipeline.data import DataConfig

    fields = {f.name for f in dataclasses.fields(DataConfig)}
    return [f"data.{o}" if o.partition("=")[0] in fields else o for o in overrides]


@releases_locks  # the --out lock ends with main, however main is called
def main(argv: list[str]) -> None:
    args = parse_args(argv)
    from pipeline import data

    config = load_config(args.config, _normalise_overrides(args.overrides))
    cfg = data.data_config(config)
    if args.workers is not None and args.workers < 1:
        raise UserError(f"--workers must be >= 1, got {args.workers}")
    out = Path(args.out).expanduser().resolve()
    if args.from_meshes and not Path(args.from_meshes).is_dir():
        raise UserError(f"--from-meshes {args.from_meshes}: not a directory")
    claim_output(out, args.overwrite, {"--from-meshes": args.from_meshes})  # one job per --out; never an input

    start = time.perf_counter()
    with staged_output_dir(out, args.overwrite) as tmp:
        if args.from_meshes:
            manifest = data.import_mesh_sequences(
                args.from_meshes,
                tmp,
                frames=cfg.frames,
                seed=cfg.seed,
                test_target_fraction=cfg.target_identities_test / (cfg.target_identities_train + cfg.target_identities_test),
                unseen_instance_fraction=cfg.unseen_instance_fraction,
                heldout_actions=cfg.heldout_actions if isinstance(cfg.heldout_actions, tuple) else (),
                progress=not args.no_progress,
            )
        else:
            import logging

            from pipeline.cluster import connect

            logging.getLogger("ray.data").setLevel(logging.ERROR)  # our progress bar, not Ray Data's logs
            connect()
            exit_on_sigterm()  # after ray.init, which installs its own handler
            manifest = data.generate_bank(cfg, tmp, workers=args.workers, progress=not args.no_progress)
    seconds = time.perf_counter() - start
    c = manifest.counts
    size = sum(s["bytes"] for s in manifest.shards)
    print(
        f"wrote {c['meshes']:,} meshes ({c['sequences']} sequences, {c['motions']} motion instances, "
        f"{c['identities']} identities, {manifest.num_vertices:,} vertices) in {c['shards']} shards, "
        f"{size / 1e6:.1f} MB, {seconds:.1f} s ({c['meshes'] / seconds:,.0f} meshes/s)"
    )
    print(f"bank: {out}")
    print(f"manifest: {out / data.MANIFEST}")


def cli() -> None:
    """The ``aniformer-generate-data`` command: `main` with one-line errors and exit codes."""
    run(main)


if __name__ == "__main__":
    cli()
