"""What a training job's console shows: a progress bar per epoch on rank 0, one summary line per
epoch, and Ray's own INFO chatter turned down (its warnings and errors stay).

`Console` travels in `train_loop_config` to the workers: the driver decides (is its stderr a terminal,
`--no-progress`, `--verbose`), rank 0 shows. The bar is `ray.experimental.tqdm_ray`, which the driver
draws from the worker's state updates (a plain tqdm in a worker would reach the driver's log as one
line of carriage returns).
"""

from __future__ import annotations

import builtins
import logging
import math
import sys
import time
from collections.abc import Callable
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from functools import partial

# INFO-level loggers of Ray Data / Ray Train that speak per dataset or per epoch: "Dataset ... execution
# finished", "... registers for logging while another dataset ...", "Progress bars disabled" (a
# warning about our own choice to disable them, hence its logger to ERROR).
QUIET_LOGGERS = {"ray.data": logging.WARNING, "ray.data._internal.progress": logging.ERROR,
                 "ray.train": logging.WARNING}


@dataclass(frozen=True)
class Console:
    progress: bool = False  # a tqdm bar per epoch on rank 0 (driver's stderr is a terminal)
    epoch_lines: bool = True  # one summary line per epoch on rank 0
    verbose: bool = False  # Ray's own INFO logs as Ray prints them

    @classmethod
    def for_job(cls, *, no_progress: bool = False, verbose: bool = False) -> Console:
        return cls(progress=not no_progress and sys.stderr.isatty(), verbose=verbose)

    def to_dict(self) -> dict:
        return asdict(self)

    @property
    def train_log_level(self) -> str:
        """Ray Train's `LoggingConfig.log_level` (its TrainingReport dumps, checkpoint lines are INFO)."""
        return "INFO" if self.verbose else "WARNING"


def quiet_ray(verbose: bool = False) -> None:
    """Turn Ray Data's and Ray Train's INFO chatter down in this process (driver or worker)."""
    if verbose:
        return
    import ray.data  # noqa: F401  (its import configures its loggers: first, then ours)

    levels = dict(QUIET_LOGGERS)
    try:  # "Reporting training result N: TrainingReport(...)": a logger named by its file, outside "ray.train"
        from ray.train.v2._internal.execution import context

        levels[context.__file__] = logging.WARNING
    except ImportError:
        pass
    for name, level in levels.items():
        logging.getLogger(name).setLevel(level)


def show(line: str) -> None:
    """Print a line once: in a Ray Train worker the patched `print` both tees to stdout and logs to the
    console (the line reached the driver twice); the real stdout goes to the driver's console once."""
    print(line, file=sys.__stdout__ or sys.stdout, flush=True)


@contextmanager
def plain_print():
    """`print` to the real stdout meanwhile: tqdm_ray's state updates, printed through Ray Train's
    patched `print`, otherwise reach the driver twice, the second time as an empty prefixed line."""
    saved = builtins.print
    builtins.print = partial(saved, file=sys.__stdout__ or sys.stdout)
    try:
        yield
    finally:
        builtins.print = saved


def short(x: float) -> str:
    """A loss in 2 significant digits: 6.1e-4, 0.034 -> 3.4e-2; nan stays nan."""
    if not math.isfinite(x):
        return str(x)
    mantissa, exponent = f"{x:.1e}".split("e")
    return f"{mantissa}e{int(exponent)}"


def epoch_line(metrics: dict, epochs: int, seconds: float) -> str:
    """The per-epoch summary of the metrics train_func reports (PMD in its x1e-4 units)."""
    nan = float("nan")
    line = (f"epoch {metrics['epoch']}/{epochs}  loss {short(metrics['loss'])} "
            f"(rec {short(metrics.get('loss_rec', nan))}, motion {short(metrics.get('loss_motion', nan))}, "
            f"appearance {short(metrics.get('loss_appearance', nan))})")
    if "pmd_seen" in metrics or "pmd_unseen" in metrics:
        line += f"  PMD seen {metrics.get('pmd_seen', nan):.1f} unseen {metrics.get('pmd_unseen', nan):.1f}"
    return line + f"  {metrics.get('samples_per_s', nan):.0f} samples/s  {seconds:.0f} s"


class EpochBar:
    """Rank 0's bar over one epoch's steps (no-op when disabled): steps, loss, samples/s, ETA."""

    INTERVAL_S = 1.0  # the loss is read (a device sync) at most this often

    def __init__(self, enabled: bool, epoch: int, epochs: int, steps: int, samples_per_step: int):
        self.bar, self.prefix, self.samples_per_step = None, f"epoch {epoch}/{epochs}", samples_per_step
        self.started = self.shown = time.perf_counter()
        self.done = 0
        if enabled:
            from ray.experimental import tqdm_ray

            with plain_print():
                self.bar = tqdm_ray.tqdm(desc=self.prefix, total=steps, unit="step")

    def step(self, mean_loss: Callable[[], float]) -> None:
        """One step done; `mean_loss` (the epoch's running mean) is called only when the bar redraws."""
        if self.bar is None:
            return
        self.done += 1
        now = time.perf_counter()
        with plain_print():
            if now - self.shown >= self.INTERVAL_S:
                self.shown = now
                rate = self.done * self.samples_per_step / (now - self.started)
                self.bar.set_description(f"{self.prefix}  loss {short(mean_loss())}  {rate:.0f} samples/s")
            self.bar.update(1)

    def close(self) -> None:
        if self.bar is not None:
            with plain_print():
                self.bar.close()
