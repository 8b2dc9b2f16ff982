"""The ``data:`` section of a config (`DataConfig`), the pair splits, the motion instances it defines
and the seeds derived from it.

Which fields shape the bank's bytes (`GENERATION_FIELDS`) and which only shape pairs or execution is
declared here, so a bank can be checked against a config (`bank.check_bank_matches`).
"""

from __future__ import annotations

import dataclasses
import zlib
from collections.abc import Sequence
from typing import Any

import numpy as np

from aniformer.config import Section, from_dict
from aniformer.geometry import CENTER_MODES
from aniformer.synth.bodies import TOPOLOGIES
from aniformer.synth.motions import ACTIONS
from aniformer.synth.stream import PAIR_FIELDS

SHUFFLE_MODES = ("none", "target", "both")
SOURCES = ("bank", "stream")  # pairs from a mesh bank on disk, or made on the fly (aniformer.synth.stream)

#: A bank's pair splits: name -> (motion-instance group, target-identity group, description). The stream's
#: are ``aniformer.synth.stream.STREAM_SPLITS``.
BANK_SPLITS: dict[str, tuple[str, str, str]] = {
    "train": ("seen", "train", "seen motion instances of seen driving identities x train targets"),
    "seen": ("seen", "test", "paper's 'seen motions': seen motion instances x unseen (test) targets"),
    "unseen": (
        "unseen",
        "test",
        "paper's 'unseen motions': held-out instances of seen drivers x test targets",
    ),
    "unseen_drivers": (
        "unseen_driver",
        "test",
        "instances performed by unseen driving identities x test targets",
    ),
    "heldout_actions": ("heldout", "test", "instances of held-out action classes x test targets"),
}

# Config fields that shape the bank itself (the rest only shape pairs or execution).
GENERATION_FIELDS = (
    "topology",
    "seed",
    "frames",
    "driving_identities",
    "unseen_driving_identities",
    "target_identities_train",
    "target_identities_test",
    "actions",
    "heldout_actions",
    "instances_per_action",
    "unseen_instance_fraction",
)
# Fields that do not change any output byte (left out of the manifest).
EXECUTION_FIELDS = ("workers",)


def _tag(name: str) -> int:
    return zlib.crc32(name.encode())


def derive_seed(seed: int, *keys: int | str) -> int:
    """A 32-bit seed derived from ``seed`` and keys (strings are hashed), stable across runs."""
    entropy = [int(seed)] + [_tag(k) if isinstance(k, str) else int(k) for k in keys]
    return int(np.random.SeedSequence(entropy).generate_state(1, np.uint32)[0])


def check_int(name: str, value: Any, low: int, high: int | None = None) -> None:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    if value < low or (high is not None and value > high):
        bound = f">= {low}" if high is None else f"in [{low}, {high}]"
        raise ValueError(f"{name} must be {bound}, got {value}")


def check_choice(name: str, value: Any, choices: Sequence[str]) -> None:
    if value not in choices:
        raise ValueError(f"{name} must be one of {', '.join(choices)}; got {value!r}")


@dataclasses.dataclass(frozen=True)
class DataConfig(Section):
    """The ``data:`` section of a config: where pairs come from and how they are drawn.

    ``source``: ``bank`` (a mesh bank on disk, described by the fields below) or ``stream`` (pairs
    made on the fly by ``aniformer.synth.stream``: fresh bodies and smooth motion over the whole
    pose space; only ``topology``, ``extra_topologies``, ``seed``, ``window``, ``center`` and the pair counts apply).

    ``extra_topologies`` (stream only): further Anny topologies trained on in turn with ``topology``, one
    topology per batch, so that the learned correction fits the transfer at each resolution it runs on;
    the epoch's pairs are shared equally and validation scores every topology.

    Identities: ``driving_identities`` perform the motion instances (the last
    ``unseen_driving_identities`` of them only for the ``unseen_drivers`` split); target identities
    are ``target_identities_train`` (training) + ``target_identities_test`` (evaluation).
    Motions: ``instances_per_action`` instances of each action in ``actions`` ("all" or names);
    ``heldout_actions`` (names, or a count drawn by seed) are never trained on; a fraction
    ``unseen_instance_fraction`` of the seen drivers' other instances is held out ("unseen").
    """

    source: str = "bank"
    topology: str = "notoes_collapse10pc"
    extra_topologies: tuple[str, ...] = ()
    seed: int = 0
    frames: int = 30
    driving_identities: int = 10
    unseen_driving_identities: int = 4
    target_identities_train: int = 16
    target_identities_test: int = 8
    actions: Any = "all"
    heldout_actions: Any = ()
    instances_per_action: int = 8
    unseen_instance_fraction: float = 0.2
    pairs_per_epoch: int = 8000
    eval_pairs: int = 1000
    window: int = 3
    shuffle: str = "target"
    center: str = "mesh"
    shard_mb: float = 64.0
    workers: int = 0  # generation workers; 0 = one per CPU of the Ray cluster

    def __post_init__(self):
        super().__post_init__()
        if self.topology not in TOPOLOGIES:
            raise ValueError(f"topology must be one of {', '.join(TOPOLOGIES)}; got {self.topology!r}")
        for extra in self.extra_topologies:
            check_choice("extra_topologies", extra, TOPOLOGIES)
        if len(set(self.train_topologies)) != len(self.train_topologies):
            raise ValueError("extra_topologies repeats a topology (or topology itself)")
        if self.extra_topologies and self.source != "stream":
            raise ValueError("extra_topologies needs source: stream (a bank holds one topology)")
        check_int("seed", self.seed, 0, 2**32 - 1)
        check_int("frames", self.frames, 2, 10_000)
        check_int("window", self.window, 1, self.frames)
        check_int("driving_identities", self.driving_identities, 1, 100_000)
        check_int("unseen_driving_identities", self.unseen_driving_identities, 0, self.driving_identities - 1)
        check_int("target_identities_train", self.target_identities_train, 1, 100_000)
        check_int("target_identities_test", self.target_identities_test, 0, 100_000)
        check_int("instances_per_action", self.instances_per_action, 1, 100_000)
        check_int("pairs_per_epoch", self.pairs_per_epoch, 1, 10**9)
        check_int("eval_pairs", self.eval_pairs, 1, 10**9)
        check_int("workers", self.workers, 0, 100_000)
        fraction = self.unseen_instance_fraction
        if isinstance(fraction, bool) or not isinstance(fraction, (int, float)) or not 0 <= fraction < 1:
            raise ValueError(f"unseen_instance_fraction must be a number in [0, 1), got {fraction!r}")
        shard_mb = self.shard_mb
        if isinstance(shard_mb, bool) or not isinstance(shard_mb, (int, float)) or not shard_mb > 0:
            raise ValueError(f"shard_mb must be a positive number, got {shard_mb!r}")
        check_choice("shuffle", self.shuffle, SHUFFLE_MODES)
        check_choice("center", self.center, CENTER_MODES)
        check_choice("source", self.source, SOURCES)
        if self.source == "stream" and self.shuffle != "none":
            raise ValueError("source=stream makes driver and target on one topology: shuffle must be none")
        self.resolved_actions()  # validates actions / heldout_actions
        groups = {m["split"] for m in assign_motions(self)}
        if "seen" not in groups:
            raise ValueError(
                "no seen motion instance is left for training: lower unseen_instance_fraction "
                "or unseen_driving_identities, or raise instances_per_action"
            )

    def resolved_actions(self) -> tuple[tuple[str, ...], tuple[str, ...]]:
        """(actions in library order, held-out actions)."""
        library = tuple(ACTIONS)
        if isinstance(self.actions, str):
            if self.actions != "all":
                raise ValueError(f"actions must be 'all' or a list of action names; got {self.actions!r}")
            actions = library
        else:
            chosen = list(self.actions)
            unknown = [a for a in chosen if a not in library]
            if unknown or not chosen:
                raise ValueError(f"unknown action(s) {unknown or '(empty list)'}; known: {', '.join(library)}")
            if len(set(chosen)) != len(chosen):
                raise ValueError("actions lists an action twice")
            actions = tuple(a for a in library if a in chosen)
        held = self.heldout_actions
        if isinstance(held, int) and not isinstance(held, bool):
            check_int("heldout_actions (a count)", held, 0, len(actions) - 1)
            order = np.random.default_rng(derive_seed(self.seed, "heldout")).permutation(len(actions))
            heldout = tuple(actions[i] for i in sorted(order[:held]))
        elif isinstance(held, (list, tuple)):
            bad = [a for a in held if a not in actions]
            if bad:
                raise ValueError(f"heldout_actions {bad} not among the chosen actions")
            heldout = tuple(a for a in actions if a in held)
            if len(heldout) >= len(actions):
                raise ValueError("heldout_actions must leave at least one action for training")
        else:
            raise ValueError(f"heldout_actions must be a list of action names or a count; got {held!r}")
        return actions, heldout

    @property
    def train_topologies(self) -> tuple[str, ...]:
        """The topologies trained on, one per batch in turn: ``topology`` first."""
        return (self.topology, *self.extra_topologies)

    def pair_settings(self) -> dict:
        """The fields a pair sampler takes (``PairSampler(bank, **cfg.pair_settings())``)."""
        return {k: getattr(self, k) for k in PAIR_FIELDS}

    def generation_dict(self) -> dict:
        """The fields that shape the bank, as plain JSON values."""
        plain = self.to_dict()
        return {k: plain[k] for k in GENERATION_FIELDS}


def assign_motions(cfg: DataConfig) -> list[dict]:
    """Motion instances with their driving identity and split group, a pure function of ``cfg``.

    Regular instances go round-robin (ordered by instance, then action, so every driver gets a
    mix of actions) over all driving identities in a seeded order; held-out-action instances go
    to seen drivers only (so the action class is the only novelty). Among the seen drivers'
    regular instances a seeded ``unseen_instance_fraction`` becomes "unseen" (at least one when
    the fraction is positive, never all of them).
    """
    library = tuple(ACTIONS)
    actions, heldout = cfg.resolved_actions()
    n_seen = cfg.driving_identities - cfg.unseen_driving_identities
    rng = np.random.default_rng(derive_seed(cfg.seed, "drivers"))
    drivers = [int(d) for d in rng.permutation(cfg.driving_identities)]
    seen_drivers = [d for d in drivers if d < n_seen]
    motions = []
    for action in actions:
        for instance in range(cfg.instances_per_action):
            motions.append(
                {
                    "name": f"{action}-{instance:03d}",
                    "action": action,
                    "instance": instance,
                    "seed": derive_seed(cfg.seed, "motion", library.index(action), instance),
                }
            )
    regular = sorted(
        (m for m in motions if m["action"] not in heldout),
        key=lambda m: (m["instance"], actions.index(m["action"])),
    )
    for j, m in enumerate(regular):
        m["driver"] = drivers[j % len(drivers)]
        m["split"] = "seen" if m["driver"] < n_seen else "unseen_driver"
    held = sorted(
        (m for m in motions if m["action"] in heldout),
        key=lambda m: (m["instance"], actions.index(m["action"])),
    )
    for j, m in enumerate(held):
        m["driver"] = seen_drivers[j % len(seen_drivers)]
        m["split"] = "heldout"
    candidates = [i for i, m in enumerate(motions) if m["split"] == "seen"]
    if cfg.unseen_instance_fraction > 0 and len(candidates) >= 2:
        count = min(len(candidates) - 1, max(1, round(cfg.unseen_instance_fraction * len(candidates))))
        picked = np.random.default_rng(derive_seed(cfg.seed, "unseen")).permutation(candidates)[:count]
        for i in picked:
            motions[int(i)]["split"] = "unseen"
    for i, m in enumerate(motions):
        m["id"] = i
    return motions


def data_config(config: dict) -> DataConfig:
    """``DataConfig`` from a whole loaded config (its ``data:`` section); `UserError` if bad."""
    return from_dict(DataConfig, (config or {}).get("data"), "data")
