"""Shared command-line plumbing for the jobs: `--config FILE` plus `key=value` overrides,
one-line errors for bad input, and atomic writes so no half-written file is ever left behind.

Every job's `main` raises `UserError` for anything the user can fix; `run` turns it into one line
on stderr and exit status 2 (the convention of argparse itself).

Configs are read with `ConfigLoader`: YAML's anchors and aliases are allowed (configs/seeds.yaml
names an override once), but a document whose aliases would expand to more than `MAX_CONFIG_NODES`
nodes (a "billion laughs" bomb) or refer to themselves is refused as it is composed, before anything
is built from it.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import dataclasses
import os
import shutil
import sys
import tempfile
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import yaml


class UserError(Exception):
    """Bad input the user can fix: reported as one line, exit status 2."""


class ArgumentParser(argparse.ArgumentParser):
    """argparse whose usage errors are a `UserError` (one line, exit 2 through `run`)."""

    def error(self, message):
        raise UserError(f"{message} (see --help)")


# A config has a few hundred nodes; nine nested aliases of ten already expand to 10^9.
MAX_CONFIG_NODES = 100_000


def _expanded_nodes(root: yaml.Node) -> int:
    """Nodes of `root` with every alias expanded, counted once per distinct node (linear in the
    document's size); `UserError` on a node that contains itself."""
    sizes: dict[int, int] = {}
    open_nodes: set[int] = set()

    def size(node: yaml.Node) -> int:
        key = id(node)
        if key in sizes:
            return sizes[key]
        if key in open_nodes:
            raise UserError(f"a YAML alias refers to the node that contains it (line {node.start_mark.line + 1})")
        open_nodes.add(key)
        if isinstance(node, yaml.SequenceNode):
            total = 1 + sum(size(child) for child in node.value)
        elif isinstance(node, yaml.MappingNode):
            total = 1 + sum(size(k) + size(v) for k, v in node.value)
        else:
            total = 1
        open_nodes.discard(key)
        sizes[key] = min(total, MAX_CONFIG_NODES + 1)  # capped: the counts of a bomb stay small integers
        return sizes[key]

    return size(root)


class ConfigLoader(yaml.SafeLoader):
    """`yaml.SafeLoader` that bounds alias expansion: each document is measured as it is composed,
    before a Python object is constructed from it."""

    def compose_document(self):
        node = super().compose_document()
        if _expanded_nodes(node) > MAX_CONFIG_NODES:
            raise UserError(f"YAML aliases expand to more than {MAX_CONFIG_NODES:,} nodes (an alias bomb?)")
        return node


def parse_yaml(text: str):
    """`text` parsed as a config (YAML, with `ConfigLoader`'s bound on alias expansion)."""
    return yaml.load(text, Loader=ConfigLoader)  # noqa: S506 (a SafeLoader subclass)


def load_config(path: str | os.PathLike | None, overrides: Sequence[str] = ()) -> dict:
    """Read a YAML config and apply dotted `key=value` overrides (values parsed as YAML)."""
    config: dict = {}
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise UserError(f"config file not found: {path}")
        try:
            config = parse_yaml(path.read_text()) or {}
        except yaml.YAMLError as e:
            raise UserError(f"config {path} is not valid YAML: {str(e).splitlines()[0]}") from None
        except UserError as e:
            raise UserError(f"config {path}: {e}") from None
        if not isinstance(config, dict):
            raise UserError(f"config {path} must be a mapping at the top level")
    return apply_overrides(config, overrides)


def apply_overrides(config: dict, overrides: Sequence[str]) -> dict:
    """`config` (a deep copy) with dotted `key=value` overrides applied; a whole section may be
    replaced too (`model={name: npt, channels: [64, 32]}`)."""
    config = copy.deepcopy(config)
    for item in overrides:
        key, sep, raw = str(item).partition("=")
        if not sep or not key:
            raise UserError(f"override {item!r} is not of the form key=value")
        try:
            value = parse_yaml(raw)
        except yaml.YAMLError:
            value = raw
        except UserError as e:
            raise UserError(f"override {key}: {e}") from None
        node = config
        *parents, leaf = key.split(".")
        for part in parents:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise UserError(f"override {item!r}: {part!r} is not a section")
        node[leaf] = value
    return config


def from_dict(cls: type, values: dict | None, section: str):
    """Build dataclass `cls` from a config section, naming unknown keys and bad values in one line."""
    values = dict(values or {})
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - names)
    if unknown:
        raise UserError(f"unknown key(s) in [{section}]: {', '.join(unknown)} (known: {', '.join(sorted(names))})")
    for f in dataclasses.fields(cls):  # YAML gives lists where the dataclass holds tuples
        if isinstance(values.get(f.name), list):
            values[f.name] = tuple(values[f.name])
    try:
        return cls(**values)
    except (TypeError, ValueError) as e:
        raise UserError(f"[{section}] {e}") from None


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside `path`; rename it into place only if the block succeeds."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600 files; give the mode a plain open() would
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


class RunJobParser(ArgumentParser):
    """The arguments of the jobs that run on Ray (train, sweep, ablate): `--config FILE`, `--out DIR`,
    `--name`, `--bank`, `--experiment` and `key=value` overrides."""

    def __init__(self, prog: str, doc: str, out_help: str, name_help: str):
        super().__init__(prog=prog, description=doc.split("\n\n")[0])
        self.add_argument("--config", required=True, metavar="FILE")
        self.add_argument("--out", required=True, metavar="DIR", help=out_help)
        self.add_argument("--name", default=None, help=f"{name_help} (default: OUT's name)")
        self.add_argument("--bank", default=None, metavar="DIR", help="an existing mesh bank (default: OUT/bank)")
        self.add_argument("--experiment", default="aniformer", help="MLflow experiment")
        self.add_argument("overrides", nargs="*", metavar="key=value")

    @staticmethod
    def locations(args: argparse.Namespace) -> tuple[Path, str, Path]:
        """(out, job name, bank) of parsed arguments; `out` is created and locked for this job
        (`files.lock_output`: a second job on it is refused), the name checked."""
        from aniformer.files import lock_output

        out = Path(args.out).expanduser().resolve()
        name = job_name(args.name or out.name)
        lock_output(out)
        return out, name, Path(args.bank).expanduser().resolve() if args.bank else out / "bank"


def job_name(name: str) -> str:
    """A job name (`--name`): it names directories under `--out`, so it must be one plain path
    component, never `..` or a path that leads elsewhere."""
    if not name or name in (".", "..") or "/" in name or "\\" in name or "\0" in name:
        raise UserError(f"--name {name!r}: must be a plain name (no '/', not '.' or '..')")
    return name


def check_output_dir(out: Path, overwrite: bool) -> None:
    """Refuse an `--out` that is a file, or a non-empty directory unless `overwrite` (a job's own lock
    file does not count)."""
    from aniformer.files import LOCK_NAME

    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} exists and is not a directory")
    if out.is_dir() and any(p.name != LOCK_NAME for p in out.iterdir()) and not overwrite:
        raise UserError(f"--out {out} exists and is not empty; pass --overwrite to replace it")


@contextlib.contextmanager
def staged_output_dir(out: Path, overwrite: bool) -> Iterator[Path]:
    """Yield a temporary directory beside `out`; when the block succeeds it replaces `out`.

    A failure (or Ctrl-C) leaves `out` as it was and removes the partial directory; what a killed
    job left beside `out` is removed first (`files.clean_stale_staging`). When this process holds the
    lock on `out` (`files.lock_output`), the new directory is locked too before it takes `out`'s place,
    and the two are exchanged atomically, so no other job can slip in between.
    """
    from aniformer import files

    check_output_dir(out, overwrite)
    out.parent.mkdir(parents=True, exist_ok=True)
    files.clean_stale_staging(out)
    tmp = files.staging_dir(out)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o777 & ~umask)  # mkdtemp makes it private; the results are an ordinary directory
    try:
        yield tmp
        check_output_dir(out, overwrite)  # still true after a long job?
        lock = files.held_lock(out)
        if lock is not None and lock.directory == Path(os.path.abspath(out)):
            lock.add(tmp)  # the new `out` is locked as it appears
        if out.exists() and files.swap_dirs(tmp, out):
            shutil.rmtree(tmp, ignore_errors=True)  # now the old `out`
            return
        old = None
        if out.exists():
            old = out.with_name(f".{out.name}.old-{os.getpid()}")
            os.replace(out, old)
        os.replace(tmp, out)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


_terminated = False


def _on_sigterm(signum, frame):
    global _terminated
    _terminated = True
    raise SystemExit(143)


def exit_on_sigterm() -> None:
    """(Re)install `run`'s SIGTERM handler: exit 143 with one line. A job calls it again after
    `ray.init`, which installs a handler of its own (it prints a stack and kills the process)."""
    import signal

    signal.signal(signal.SIGTERM, _on_sigterm)


def terminated() -> bool:
    """Whether this process was sent SIGTERM (`ray job stop`, kill) while `run` ran its job."""
    return _terminated


def run(main: Callable[[list[str]], Any], argv: list[str] | None = None) -> None:
    """Call `main(argv)`; a `UserError` becomes one line on stderr and exit status 2, Ctrl-C 130,
    SIGTERM 143 (whatever the stack made of the `SystemExit` it raises), a full disk one line and 1.
    Output locks the job took (`files.lock_output`) are released as it ends."""
    import errno
    import signal

    from aniformer.files import release_locks

    global _terminated
    _terminated = False
    try:
        previous = signal.signal(signal.SIGTERM, _on_sigterm)
    except ValueError:  # not the main thread
        previous = None
    try:
        main(sys.argv[1:] if argv is None else argv)
    except BaseException as e:
        if _terminated:
            print("terminated (SIGTERM)", file=sys.stderr)
            sys.exit(143)
        if isinstance(e, UserError):
            print(f"error: {e}", file=sys.stderr)
            sys.exit(2)
        if isinstance(e, KeyboardInterrupt):
            print("interrupted", file=sys.stderr)
            sys.exit(130)
        if isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT):
            print(f"error: no space left on the device ({e.filename or e}); nothing partial was kept",
                  file=sys.stderr)
            sys.exit(1)
        raise
    finally:
        release_locks()
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    if _terminated:  # the stack swallowed the SystemExit and returned
        print("terminated (SIGTERM)", file=sys.stderr)
        sys.exit(143)
