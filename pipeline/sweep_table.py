"""A sweep's trials as a table: the live console table (`SweepReporter`, Tune's CLI reporter protocol),
the final summary (`summary.csv`), the best trial, and the link to the trials' compare view in `mlflow ui`."""

from __future__ import annotations

import csv
import json
import math
import time
from pathlib import Path
from urllib.parse import quote

from ray.tune import CLIReporter

from aniformer.io.files import atomic_path
from pipeline.sweep_config import SweepConfig
from pipeline.tracking import Tracker, tracking_uri
from pipeline.tune import STATUSES, SUMMARY_FIELDS, decision_fields, last_result, plan_trial, trial_status


def summarize(results, sweep: SweepConfig, epochs: int) -> list[dict]:
    """One row per trial (SUMMARY_FIELDS), in trial-id order."""
    trials = results._experiment_analysis.trials  # same order as the results; no public accessor in 2.60
    return sorted((trial_row(trial, sweep, epochs) for trial in trials), key=lambda r: str(r["trial_id"]))


def trial_row(trial, sweep: SweepConfig, epochs: int, planned: dict | None = None) -> dict:
    """The SUMMARY_FIELDS row of a Tune trial. A trial still pending or running has status `pending`
    or `running` (`paused`, ...: Tune's own, lower-cased); `planned` (its `decision_fields`, what the
    trial will report) fills the memory columns of a trial that has not reported yet."""
    metrics = {**(planned or {}), **last_result(trial)}
    config = trial.config or {}
    if trial.status in ("TERMINATED", "ERROR"):
        status = trial_status(metrics, "error" if trial.status == "ERROR" else None, epochs)
    else:
        status = str(trial.status).lower()
    best = (trial.metric_analysis.get(sweep.metric) or {}).get("min", math.nan)
    return {
        "trial_id": trial.trial_id, "status": status, "memory_decision": metrics.get("memory_decision", ""),
        "rec": config.get("rec"), "motion": config.get("motion"), "appearance": config.get("appearance"),
        "window": config.get("window"), "lr": config.get("lr", ""),
        "batch_size": metrics.get("requested_batch_size", config.get("batch_size", "")),
        "run_batch_size": metrics.get("run_batch_size", "") if status != "skipped_memory" else "",
        "grad_accumulation": metrics.get("grad_accumulation", ""),
        "predicted_memory_gb": _round(metrics.get("predicted_memory_gb")),
        "requested_memory_gb": _round(metrics.get("requested_memory_gb")),
        "measured_memory_gb": _round(metrics.get("peak_memory_gb")),
        "memory_limit_gb": sweep.memory_limit_gb if sweep.memory_limit_gb is not None else "",
        "epochs": int(metrics.get("epoch", 0) or 0), "best_pmd_unseen": _round(best, 4),
        "mlflow_run_id": metrics.get("mlflow_run_id", ""),
    }


def _round(value, digits: int = 3):
    if value is None:
        return ""
    value = float(value)
    return round(value, digits) if math.isfinite(value) else ""


# The console table's columns: (header, the row's field or a function of the row, right-aligned)
def _batch(row: dict) -> str:
    requested, run, accumulation = row["batch_size"], row["run_batch_size"], row["grad_accumulation"]
    if row["memory_decision"] == "skipped_memory":
        return f"{requested} (skip)"  # fits in no batch within max_grad_accumulation: never built
    if run in ("", None) or run == requested:
        return str(requested)
    return f"{requested}->{run}x{accumulation}"  # adjusted: micro-batch x accumulation


def _fmt(value, spec: str) -> str:
    if value in ("", None):
        return ""
    return format(value, spec) if isinstance(value, (int, float)) else str(value)


TABLE_COLUMNS = (
    ("trial", lambda r, e: str(r["trial_id"]), False),
    ("status", lambda r, e: r["status"], False),
    ("rec", lambda r, e: _fmt(r["rec"], ".3g"), True),
    ("motion", lambda r, e: _fmt(r["motion"], ".3g"), True),
    ("appearance", lambda r, e: _fmt(r["appearance"], ".3g"), True),
    ("T", lambda r, e: _fmt(r["window"], "d"), True),
    ("lr", lambda r, e: _fmt(r["lr"], ".3g"), True),
    ("batch", lambda r, e: _batch(r), True),
    ("pred GB", lambda r, e: _fmt(r["requested_memory_gb" if r["memory_decision"] == "skipped_memory"
                                    else "predicted_memory_gb"], ".2f"), True),
    ("peak GB", lambda r, e: _fmt(r["measured_memory_gb"], ".2f"), True),
    ("epoch", lambda r, e: f"{r['epochs']}/{e}" if r["epochs"] or r["status"] == "running" else "", True),
    ("best PMD", lambda r, e: _fmt(r["best_pmd_unseen"], ".4g"), True),
)


def format_table(rows: list[dict], epochs: int) -> str:
    """Trial rows (`trial_row`, `summarize`) as a psql-style table, as Tune's CLIReporter draws one:
    trial, status, the loss weights (rec, motion, appearance), the window T, [lr], the batch
    (requested->micro-batch x accumulation when the memory gate adjusted it), predicted and measured
    per-worker GB, epochs done, best validation PMD (unseen, x1e-4). Columns empty in every row are left out."""
    cells = [[get(row, epochs) for _, get, _ in TABLE_COLUMNS] for row in rows]
    keep = [i for i, (name, _, _) in enumerate(TABLE_COLUMNS) if name in ("trial", "status") or any(c[i] for c in cells)]
    headers = [TABLE_COLUMNS[i][0] for i in keep]
    widths = [max([len(headers[j])] + [len(c[i]) for c in cells]) for j, i in enumerate(keep)]

    def line(values) -> str:
        out = []
        for j, (i, value) in enumerate(zip(keep, values)):
            out.append(value.rjust(widths[j]) if TABLE_COLUMNS[i][2] else value.ljust(widths[j]))
        return "| " + " | ".join(out) + " |"

    rule = "+-" + "-+-".join("-" * w for w in widths) + "-+"
    body = [line([c[i] for i in keep]) for c in cells]
    return "\n".join([rule, line(headers), rule.replace("+", "|", 1)[:-1] + "|", *body, rule])


def _counts(rows: list[dict]) -> str:
    counts: dict[str, int] = {}
    for row in rows:
        counts[row["status"]] = counts.get(row["status"], 0) + 1
    return ", ".join(f"{n} {status}" for status, n in sorted(counts.items()))


def _duration(seconds: float) -> str:
    minutes, seconds = divmod(int(seconds), 60)
    return f"{minutes} min {seconds:02d} s" if minutes else f"{seconds} s"


class SweepReporter(CLIReporter):
    """The sweep's console: Tune's progress-reporter protocol (`should_report`/`report`, driven by
    Tune's loop like its CLIReporter) with the sweep's own table (`format_table`): a trial's memory
    decision is predicted here before it reports (the gate `run_trial` applies), statuses are the
    sweep's (pending, running, then STATUSES), best PMD is the minimum over the trial's epochs
    (Tune's metric analysis). The table is printed when it changed, at most every `every` seconds
    (and every `heartbeat` seconds regardless), so that a log (`ray job logs`) is not flooded; the
    last one, when the sweep ends, is the summary table."""

    def __init__(self, base: dict, sweep: SweepConfig, *, sweep_name: str, epochs: int, vertices: int,
                 faces: int | None, every: float = 5.0, heartbeat: float = 300.0):
        super().__init__(max_report_frequency=every)  # metric and mode: from TuneConfig, in setup()
        self.base, self.sweep, self.sweep_name, self.epochs = base, sweep, sweep_name, epochs
        self.vertices, self.faces, self.heartbeat = vertices, faces, heartbeat
        self._planned: dict[str, dict] = {}
        self._shown: tuple = ()
        self._last_report_time = 0.0
        self._started = time.time()

    def setup(self, start_time: float | None = None, total_samples: int | None = None, **kwargs) -> None:
        super().setup(start_time=start_time, total_samples=total_samples, **kwargs)
        self._started = start_time or time.time()  # CLIReporter.set_start_time (2.60) drops the value given

    def _plan(self, trial) -> dict:
        if trial.trial_id not in self._planned:
            try:
                requested, plan = plan_trial(self.base, trial.config or {}, self.vertices, self.faces, self.sweep)
                self._planned[trial.trial_id] = decision_fields(requested, plan, self.sweep)
            except Exception:  # the trial itself will report the problem
                self._planned[trial.trial_id] = {}
        return self._planned[trial.trial_id]

    def rows(self, trials) -> list[dict]:
        """One per trial, in the order Tune created them (new trials come last)."""
        return [trial_row(t, self.sweep, self.epochs, self._plan(t)) for t in trials]

    def should_report(self, trials, done: bool = False) -> bool:
        now = time.time()
        if done:
            return True
        if now - self._last_report_time < self._max_report_freqency:
            return False
        state = tuple((r["trial_id"], r["status"], r["epochs"], r["best_pmd_unseen"]) for r in self.rows(trials))
        return state != self._shown or now - self._last_report_time >= self.heartbeat

    def report(self, trials, done: bool, *sys_info: str) -> None:
        rows = self.rows(trials)
        self._shown = tuple((r["trial_id"], r["status"], r["epochs"], r["best_pmd_unseen"]) for r in rows)
        self._last_report_time = time.time()
        self._print(self.text(rows, done, *sys_info))

    def text(self, rows: list[dict], done: bool, *sys_info: str) -> str:
        elapsed = _duration(time.time() - self._started)
        total = max(self._total_samples or 0, len(rows))
        if done:
            head = f"== sweep {self.sweep_name}: {len(rows)} trials ({_counts(rows)}) in {elapsed} =="
        else:
            finished = [r for r in rows if r["status"] in STATUSES]
            head = (f"== sweep {self.sweep_name}: {len(finished)}/{total} trials finished"
                    + (f" ({_counts(finished)})" if finished else "")
                    + f", {sum(r['status'] == 'running' for r in rows)} running"
                    + f", {sum(r['status'] == 'pending' for r in rows)} pending; {elapsed} ==")
        lines = [head]
        scored = [r for r in rows if r["best_pmd_unseen"] != "" and r["status"] != "failed"]
        if scored:
            best = min(scored, key=lambda r: r["best_pmd_unseen"])
            lines.append(f"best{'' if done else ' so far'}: trial {best['trial_id']}, "
                         f"PMD unseen {best['best_pmd_unseen']:.4g} (x1e-4)")
        lines.append(format_table(rows, self.epochs))
        return "\n".join(lines) + "\n"


def compare_url(ui: str, experiment_id: str, run_ids) -> str:
    """The MLflow UI's compare view of `run_ids` (parallel coordinates, scatter, box and contour plots
    over their params and metrics, then their params and metrics side by side) on the UI at `ui`."""

    runs = quote(json.dumps([str(r) for r in run_ids], separators=(",", ":")))
    return f"{ui.rstrip('/')}/#/compare-runs?runs={runs}&experiments={quote(json.dumps([str(experiment_id)]))}"


def compare_link(parent, rows: list[dict], ui: str | None = None) -> str | None:
    """The compare view of a sweep's trials that trained (children of the `parent` Tracker, from
    summary rows), on `ui`, else the tracking server itself (an http store), else `mlflow ui`'s default
    address. None if no trial trained."""
    ids = [r["mlflow_run_id"] for r in rows if r["mlflow_run_id"] and r["status"] not in ("skipped_memory", "failed")]
    if not ids:
        return None
    if ui is None:
        ui = parent.uri if parent.uri.startswith(("http://", "https://")) else "http://127.0.0.1:5000"
    return compare_url(ui, parent.client.get_run(parent.run_id).info.experiment_id, ids)


def write_summary(rows: list[dict], path: Path) -> Path:

    with atomic_path(path) as tmp, open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=SUMMARY_FIELDS)
        writer.writeheader()
        writer.writerows(rows)
    return path


def best_row(rows: list[dict]) -> dict | None:
    ran = [r for r in rows if r["status"] in ("ok", "adjusted_memory", "early_stopped") and r["best_pmd_unseen"] != ""]
    return min(ran, key=lambda r: r["best_pmd_unseen"]) if ran else None


def record_results(parent, rows: list[dict], best: dict | None, complete: bool) -> dict[str, int]:
    """Tag the sweep's parent run with its trial counts and, when the sweep is ``complete``, its ``best`` trial
    (`best_row`; also tagged ``best=true`` on the trial's child run); returns the counts by status."""
    if best and complete:
        Tracker(tracking_uri(), best["mlflow_run_id"]).set_tags({"best": "true"})
        parent.set_tags({"best_trial_id": best["trial_id"], "best_run_id": best["mlflow_run_id"],
                         "best_pmd_unseen": best["best_pmd_unseen"]})
        parent.log_metrics({"best_pmd_unseen": best["best_pmd_unseen"]}, step=0)
    counts: dict[str, int] = {}
    for row in rows:
        counts[row["status"]] = counts.get(row["status"], 0) + 1
    parent.set_tags({f"trials.{k}": v for k, v in counts.items()})
    return counts
