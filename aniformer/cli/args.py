"""The jobs' arguments: `--config FILE` plus `key=value` overrides, parsers whose usage errors are one line
(`aniformer.cli.exits.run` prints them), a job's options dataclass from its flags, `--name` and `--device`.

Configs are read with `ConfigLoader`: YAML's anchors and aliases are allowed (configs/seeds.yaml
names an override once), but a document whose aliases would expand to more than `MAX_CONFIG_NODES`
nodes (a "billion laughs" bomb) or refer to themselves is refused as it is composed, before anything
is built from it.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import os
import unicodedata
from collections.abc import Sequence
from pathlib import Path

import yaml

from aniformer.cli.locks import lock_output
from aniformer.errors import UserError


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
        (`lock_output`: a second job on it is refused), the name checked."""
        out = Path(args.out).expanduser().resolve()
        name = job_name(args.name or out.name)
        lock_output(out)
        return out, name, Path(args.bank).expanduser().resolve() if args.bank else out / "bank"


def options_from(kind: type, args: argparse.Namespace):
    """The options dataclass ``kind`` of a job's parsed arguments: each field from the flag of its name."""
    return kind(**{field.name: getattr(args, field.name) for field in dataclasses.fields(kind)})


def job_name(name: str) -> str:
    """A job name (`--name`, by default OUT's name): it names directories under `--out`, so it must be
    one plain path component, never `..` or a path that leads elsewhere. Any printable Unicode is a
    name (Ray Train is given an ASCII form of it, `pipeline.trainer.ray_run_name`); control characters
    and bytes that are not UTF-8 are refused, as they would break one-line messages and MLflow's tags."""
    if not name or name in (".", "..") or "/" in name or "\\" in name or "\0" in name:
        raise UserError(f"--name {name!r}: must be a plain name (no '/', not '.' or '..')")
    if any(unicodedata.category(char) in ("Cc", "Cs") for char in name):  # Cs: an undecodable byte of a path
        raise UserError(f"--name {name!r}: control characters and bytes that are not UTF-8 are not allowed; "
                        "pass another --name")
    return name


def resolve_device(name: str):
    """The torch device of a `--device` flag (`auto`: CUDA when there is one); `UserError` if unusable."""
    import torch  # only the jobs that run a model pay for it

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        device = torch.device(name)
    except RuntimeError:
        raise UserError(f"--device {name!r}: not a torch device") from None
    if device.type == "cuda" and not torch.cuda.is_available():
        raise UserError(f"--device {name}: CUDA is not available on this machine")
    return device
