"""Soak: two trainings, a sweep and an evaluation at once on this machine, with kill -9 faults (issue 34).

    python bench/soak.py --out /tmp/soak [--minutes 20] [--kill-every 120] [--seed 0]

Not a test and never run in CI: it takes --minutes of both cores. The jobs run as a user runs them,
``.venv/bin/python jobs/...`` from the repository root, each with its own local Ray and its own MLflow
store (``OUT/<round>/<job>/mlflow.db``):

    train_s0   jobs/train.py --config configs/tiny.yaml train.seed=0 train.epochs=6
    train_s1   the same with train.seed=1
    sweep      jobs/sweep.py --config configs/sweep_tiny.yaml sweep.num_samples=2 sweep.grace_period=2
    evaluate   jobs/evaluate.py --checkpoint pretrained --pairs 4 --overwrite

Steps:

1. ``reference``: the four jobs at once, undisturbed.
2. ``round 1, 2, ...``: the same four commands into fresh folders, while every ~--kill-every seconds
   (0.5x to 1.5x, at random) a random job driver or a random Ray worker (a ``ray::`` process) of a
   running job is killed with SIGKILL. A job that exits non-zero after a fault is started again with
   the same command, as a user would. A round starts while the reference's wall time still fits in
   --minutes, and runs to its end with faults (longer than the reference when restarts add up).
3. Checks, for every job of every round against the reference:
   - it exited 0 (after its restarts), and every MLflow run of its store is FINISHED (sweep.grace_period=2
     with 2 epochs: ASHA stops no trial, whose run would end KILLED by design);
   - its results are *exactly* equal to the reference's (the code is deterministic for a seed,
     docs/results.md, and a resume restores weights, optimiser and RNG, docs/guarantees.md section 5):
     train: per epoch, the last logged ``loss``, ``loss_rec``, ``loss_motion``, ``loss_appearance``,
     ``lr``, ``pmd_seen``, ``pmd_unseen``; sweep: every trial by its sampled parameters (summary.csv:
     status, memory decision, epochs, best PMD) and the same per-epoch metrics of its MLflow run;
     evaluate: every metric of its run and its results.csv byte for byte;
   - no staging leftovers (``.NAME.*.tmp``, aniformer/cli/outputs.py, aniformer/io/files.py) anywhere in its folder;
   - at the end, no process of the soak alive (every job process carries ``SOAK_TAG`` in its
     environment, inherited by its Ray's GCS, raylet and workers): each job's local Ray, and so its
     placement groups, is gone when the job exits.

Prints the faults and a markdown table; exits 1 if any check fails.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import functools
import importlib
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PYTHON = str(ROOT / ".venv" / "bin" / "python") if (ROOT / ".venv" / "bin" / "python").exists() else sys.executable
STAGING = re.compile(r"^\..+\.tmp$")  # staging dirs .NAME.PID-XXXXXXXX.tmp and atomic_path's .NAME.XXXXXXXX.tmp
TRAIN_METRICS = ("loss", "loss_rec", "loss_motion", "loss_appearance", "lr", "pmd_seen", "pmd_unseen")
SWEEP_COLUMNS = ("status", "memory_decision", "epochs", "best_pmd_unseen")
NOT_WORKERS = {"ray::IDLE", "ray::DashboardAgent", "ray::RuntimeEnvAgent"}  # Ray's agents: a node kill, not a worker's
MAX_ATTEMPTS = 6  # per job and round: more restarts than this is a failure, not a soak


def job_commands(folder: Path) -> dict[str, list[str]]:
    """The four jobs' command lines, writing into `folder/<job>/out`."""
    def out(job: str) -> str:
        return str(folder / job / "out")

    def train(seed: int) -> list[str]:  # 6 short epochs: a fault often lands mid-training, between checkpoints
        return [PYTHON, str(ROOT / "jobs/train.py"), "--config", str(ROOT / "configs/tiny.yaml"), "--no-progress",
                "--out", out(f"train_s{seed}"), "--name", f"train_s{seed}", "train.epochs=6", f"train.seed={seed}"]

    return {
        "train_s0": train(0),
        "train_s1": train(1),
        "sweep": [PYTHON, str(ROOT / "jobs/sweep.py"), "--config", str(ROOT / "configs/sweep_tiny.yaml"),
                  "--out", out("sweep"), "--name", "sweep", "sweep.num_samples=2", "sweep.grace_period=2"],
        # --overwrite: a driver killed after its rename but before its run ended leaves a complete --out
        "evaluate": [PYTHON, str(ROOT / "jobs/evaluate.py"), "--checkpoint", "pretrained",
                     "--out", out("evaluate"), "--name", "pretrained", "--pairs", "4", "--device", "cpu",
                     "--no-progress", "--overwrite"],
    }


# ------------------------------------------------------------------------------ processes

@functools.cache
def psutil():
    """Ray's vendored psutil (the project has no psutil of its own): importable once ray is imported."""
    import ray  # noqa: F401

    return importlib.import_module("psutil")


def soak_processes(tag: str) -> list:
    """Live processes whose environment carries SOAK_TAG starting with `tag` (a job, its Ray, its workers)."""
    ps = psutil()
    found = []
    for process in ps.process_iter(["pid", "name", "status"]):
        try:
            if process.info["status"] == ps.STATUS_ZOMBIE or process.pid == os.getpid():
                continue
            if process.environ().get("SOAK_TAG", "").startswith(tag):
                found.append(process)
        except ps.Error:
            pass
    return found


def name_of(process) -> str:
    try:
        return process.name()
    except Exception:  # gone meanwhile
        return "?"


@dataclasses.dataclass
class Fault:
    at: float  # seconds since the soak started
    round: str
    job: str
    kind: str  # driver | worker
    process: str
    pid: int
    survived: bool | None = None


@dataclasses.dataclass
class Job:
    """One job of one round: its command, its folder, its attempts."""
    name: str
    round: str
    folder: Path
    argv: list[str]
    env: dict
    popen: subprocess.Popen | None = None
    exits: list = dataclasses.field(default_factory=list)
    faults: list = dataclasses.field(default_factory=list)
    faulted: bool = False  # a fault hit the current attempt
    failed: str = ""

    def start(self) -> None:
        self.folder.mkdir(parents=True, exist_ok=True)
        with open(self.folder / "log.txt", "a") as log:
            log.write(f"\n===== attempt {len(self.exits) + 1}: {' '.join(self.argv)}\n")
            log.flush()
            self.popen = subprocess.Popen(self.argv, cwd=ROOT, env=self.env, stdout=log, stderr=subprocess.STDOUT,
                                          stdin=subprocess.DEVNULL)
        self.faulted = False

    @property
    def running(self) -> bool:
        return self.popen is not None and self.popen.poll() is None

    @property
    def done(self) -> bool:
        return bool(self.failed) or (bool(self.exits) and self.exits[-1] == 0)


# ------------------------------------------------------------------------------ the soak

class Soak:
    def __init__(self, args: argparse.Namespace):
        self.out = Path(args.out).resolve()
        self.minutes, self.kill_every = args.minutes, args.kill_every
        self.rng = random.Random(args.seed)
        self.start = time.monotonic()
        self.deadline = self.start + 60 * args.minutes
        self.id = f"soak-{os.getpid()}-{int(time.time())}"
        self.ray_tmp = Path(tempfile.mkdtemp(prefix="soakray-", dir="/tmp"))  # short: Ray's socket paths
        self.faults: list[Fault] = []
        self.next_kill: float | None = None  # seconds since the start
        self.rounds: dict[str, list[Job]] = {}
        self.walls: dict[str, float] = {}

    def now(self) -> float:
        return time.monotonic() - self.start

    def say(self, line: str) -> None:
        print(f"[{self.now():7.1f} s] {line}", flush=True)

    def jobs_for(self, round_name: str, index: int) -> list[Job]:
        folder = self.out / round_name
        jobs = []
        for name, argv in job_commands(folder).items():
            env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}  # each its own local Ray
            env |= {"MLFLOW_TRACKING_URI": f"sqlite:///{folder / name / 'mlflow.db'}",
                    "RAY_TMPDIR": str(self.ray_tmp / f"{index}{name[0]}{name[-1]}"),  # Ray's sockets: < 108 chars
                    "SOAK_TAG": f"{self.id}/{round_name}/{name}", "PYTHONUNBUFFERED": "1"}
            jobs.append(Job(name, round_name, folder / name, argv, env))
        return jobs

    def run_round(self, index: int, faults: bool, timeout: float) -> float:
        """Run the four jobs at once until each exited 0 or failed; restart the ones a fault brought down."""
        round_name = f"round{index}" if index else "reference"
        jobs = self.rounds[round_name] = self.jobs_for(round_name, index)
        began = time.monotonic()
        self.say(f"{round_name}: starting {', '.join(j.name for j in jobs)}")
        for job in jobs:
            job.start()
        if faults and self.next_kill is None:  # one clock across rounds: a round's end does not postpone the next fault
            self.next_kill = self.now() + self.kill_every * self.rng.uniform(0.5, 1.5)
        while not all(job.done for job in jobs):
            time.sleep(1)
            for job in jobs:
                if job.popen and not job.running:
                    self.collect(job)
            if time.monotonic() - began > timeout:
                self.give_up(jobs, f"not done after {timeout:.0f} s")
                break
            if faults and self.now() >= self.next_kill:
                self.inject(round_name, jobs)
                self.next_kill = self.now() + self.kill_every * self.rng.uniform(0.5, 1.5)
        wall = time.monotonic() - began
        self.walls[round_name] = wall
        self.say(f"{round_name}: done in {wall:.0f} s; exits " + "; ".join(f"{j.name} {j.exits}" for j in jobs))
        return wall

    def collect(self, job: Job) -> None:
        """A job's process ended: done, restarted after a fault (as a user would), or failed."""
        code = job.popen.returncode
        job.exits.append(code)
        job.popen = None
        if code == 0:
            self.say(f"{job.round}/{job.name}: exit 0")
        elif job.faulted and len(job.exits) < MAX_ATTEMPTS:
            self.say(f"{job.round}/{job.name}: exit {code} after a fault; the same command again")
            job.start()
        else:
            job.failed = f"exit {code}" + ("" if job.faulted else " without a fault") + f" (log: {job.folder}/log.txt)"
            self.say(f"{job.round}/{job.name}: FAILED, {job.failed}")

    def give_up(self, jobs: list[Job], why: str) -> None:
        for job in jobs:
            if not job.done:
                job.failed = why
                if job.running:
                    job.popen.kill()
                    job.popen.wait()

    def inject(self, round_name: str, jobs: list[Job]) -> None:
        """kill -9 a random job driver or a random Ray worker of a running job."""
        running = [job for job in jobs if job.running]
        if not running:
            return
        job = self.rng.choice(running)
        kind = self.rng.choice(["driver", "worker"])
        workers = [p for p in soak_processes(job.env["SOAK_TAG"])
                   if name_of(p).startswith("ray::") and name_of(p) not in NOT_WORKERS]
        if kind == "worker" and workers:
            victim = self.rng.choice(workers)
            pid, process = victim.pid, name_of(victim)
        else:  # no Ray worker (evaluate has no Ray, or Ray is still starting): the driver
            kind, pid, process = "driver", job.popen.pid, "driver"
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            return  # it ended in between: no fault
        fault = Fault(round(self.now(), 1), round_name, job.name, kind, process, pid)
        self.faults.append(fault)
        job.faults.append(fault)
        job.faulted = True
        self.say(f"fault: kill -9 {process} (pid {pid}) of {round_name}/{job.name}")

    def run(self) -> int:
        self.out.mkdir(parents=True, exist_ok=True)
        self.say(f"soak {self.id}: {self.minutes} min, a fault every ~{self.kill_every} s, outputs in {self.out}")
        reference = self.run_round(0, faults=False, timeout=60 * max(self.minutes, 10))
        index = 0
        while index == 0 or time.monotonic() + reference < self.deadline:  # at least one disturbed round
            index += 1
            self.run_round(index, faults=True, timeout=max(4 * reference, 600))
        self.say("all rounds done: checking")
        return self.report()

    # -------------------------------------------------------------------------- checks

    def report(self) -> int:
        leaked = self.leaked_processes()
        reference = {job.name: results(job) for job in self.rounds["reference"]}
        rows, ok = [], not leaked
        for job_name in reference:
            jobs = [r[i] for r in self.rounds.values() for i in range(len(r)) if r[i].name == job_name]
            row = self.check_job(job_name, jobs, reference[job_name])
            ok &= row.pop("ok")
            rows.append(row)
        self.print_table(rows, leaked)
        if ok:
            shutil.rmtree(self.ray_tmp, ignore_errors=True)  # Ray's logs are kept only when something failed
        print(f"\nsoak {'PASSED' if ok else 'FAILED'}; wall time {self.now() / 60:.1f} min"
              + ("" if ok else f"; Ray's logs in {self.ray_tmp}"))
        return 0 if ok else 1

    def check_job(self, name: str, jobs: list[Job], reference: dict) -> dict:
        problems, finished, equal, clean = [], 0, 0, 0
        for job in jobs:
            got = results(job)
            runs_ok = job.done and not job.failed and got["statuses"] and all(
                s == "FINISHED" for s in got["statuses"].values())
            same = not job.failed and bool(reference["values"]) and got["values"] == reference["values"]
            leftovers = staging_leftovers(job.folder)
            finished += runs_ok
            equal += same
            clean += not leftovers
            for fault in job.faults:
                fault.survived = bool(runs_ok and same and not leftovers)
            if job.failed:
                problems.append(f"{job.round}: {job.failed}")
            if not runs_ok:
                problems.append(f"{job.round}: runs {got['statuses']}")
            if not same and not job.failed:
                problems.append(f"{job.round}: differs in {differences(reference['values'], got['values'])}")
            if leftovers:
                problems.append(f"{job.round}: leftovers {leftovers[:3]}")
        faults = [f for job in jobs for f in job.faults]
        return {"job": name, "runs": len(jobs), "starts": sum(max(1, len(j.exits)) for j in jobs),
                "faults injected": len(faults), "faults survived": sum(bool(f.survived) for f in faults),
                "MLflow runs FINISHED": f"{finished}/{len(jobs)}", "results equal": f"{equal}/{len(jobs)}",
                "no staging leftovers": f"{clean}/{len(jobs)}", "problems": "; ".join(problems) or "none",
                "ok": not problems}

    def leaked_processes(self) -> list[str]:
        """The soak's processes still alive once every job ended (its Ray given 60 s to go)."""
        for _ in range(60):
            alive = soak_processes(self.id)
            if not alive:
                return []
            time.sleep(1)
        leaked = [f"{name_of(p)} (pid {p.pid})" for p in alive]
        for process in alive:  # ours: do not leave them behind on the machine
            try:
                process.kill()
            except Exception:
                pass
        return leaked

    def print_table(self, rows: list[dict], leaked: list[str]) -> None:
        print("\n## Faults\n\n| t (s) | round | job | killed | pid | survived |\n|---:|---|---|---|---:|---|")
        for f in self.faults:
            print(f"| {f.at:.0f} | {f.round} | {f.job} | {f.kind} `{f.process}` | {f.pid} | "
                  f"{'yes' if f.survived else 'NO'} |")
        columns = [c for c in rows[0] if c != "problems"]
        print("\n## Jobs\n\n| " + " | ".join(columns) + " |\n|" + "---|" * len(columns))
        for row in rows:
            print("| " + " | ".join(str(row[c]) for c in columns) + " |")
        total = {"faults injected": len(self.faults), "faults survived": sum(bool(f.survived) for f in self.faults)}
        print(f"| **all** | {sum(r['runs'] for r in rows)} | {sum(r['starts'] for r in rows)} | "
              f"{total['faults injected']} | {total['faults survived']} | | | |")
        walls = ", ".join(f"{k} {v:.0f} s" for k, v in self.walls.items())
        print(f"\nrounds: {walls}")
        print(f"leaked processes (any of the soak's jobs, their GCS, raylet, workers): {', '.join(leaked) or 'none'}")
        for row in rows:
            if row["problems"] != "none":
                print(f"problems of {row['job']}: {row['problems']}")


# ------------------------------------------------------------------------------ results

def results(job: Job) -> dict:
    """What a job produced that must equal the reference ('values'), and its MLflow runs' statuses."""
    store = job.folder / "mlflow.db"
    if not store.exists():
        return {"statuses": {}, "values": None}
    from mlflow.tracking import MlflowClient

    client = MlflowClient(f"sqlite:///{store}")
    runs = [run for exp in client.search_experiments() for run in client.search_runs([exp.experiment_id])]
    statuses = {run.info.run_name: run.info.status for run in runs}
    out = job.folder / "out"
    if job.name.startswith("train"):
        values = {run.info.run_name: histories(client, run.info.run_id, TRAIN_METRICS) for run in runs}
    elif job.name == "sweep":
        values = sweep_values(client, out / "summary.csv")
    else:  # evaluate: every metric, and the table as written
        values = {run.info.run_name: run.data.metrics for run in runs}
        table = out / "results.csv"
        values["results.csv"] = table.read_text() if table.exists() else None
    return {"statuses": statuses, "values": values}


def histories(client, run_id: str, keys: tuple[str, ...]) -> dict:
    """metric -> {step: last value logged at that step} (an epoch retrained after a fault is logged twice)."""
    found = {}
    for key in keys:
        by_step = {}
        for m in sorted(client.get_metric_history(run_id, key), key=lambda m: m.timestamp):
            by_step[m.step] = m.value
        found[key] = by_step
    return found


def sweep_values(client, summary: Path) -> dict | None:
    """Trials by their sampled parameters (trial ids are random): summary.csv's results and their runs' metrics."""
    if not summary.exists():
        return None
    with open(summary, newline="") as file:
        rows = list(csv.DictReader(file))
    values = {}
    for row in rows:
        key = ", ".join(f"{k}={row[k]}" for k in ("rec", "motion", "appearance", "window"))
        values[key] = {c: row[c] for c in SWEEP_COLUMNS}
        if row.get("mlflow_run_id"):
            values[key]["metrics"] = histories(client, row["mlflow_run_id"], TRAIN_METRICS)
    return values


def differences(expected, got, path: str = "") -> list[str]:
    """The first few paths where two nested dicts differ, with both values."""
    if isinstance(expected, dict) and isinstance(got, dict):
        found = []
        for key in sorted(set(expected) | set(got), key=str):
            found += differences(expected.get(key), got.get(key), f"{path}/{key}")
        return found[:5]
    return [] if expected == got else [f"{path}: {str(expected)[:60]} != {str(got)[:60]}"]


def staging_leftovers(folder: Path) -> list[str]:
    """Staging directories and temporary files (aniformer/cli/outputs.py, aniformer/io/files.py) left anywhere under `folder`."""
    return [str(p) for p in folder.rglob("*") if STAGING.match(p.name)]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True, help="folder for every job's outputs, logs and MLflow stores")
    parser.add_argument("--minutes", type=float, default=20, help="time for the reference and the faults (default 20)")
    parser.add_argument("--kill-every", type=float, default=120, help="mean seconds between faults (default 120)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the fault times, jobs and processes")
    soak = Soak(parser.parse_args())
    # `kill` or Ctrl-C (ignored by default under nohup ... &): stop through `finally`, which ends the jobs
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        return soak.run()
    finally:
        for process in soak_processes(soak.id):  # interrupted: end what the soak started, and only that
            try:
                process.kill()
            except Exception:
                pass


if __name__ == "__main__":
    sys.exit(main())
