"""Limits before work (issue 18, items 6 and 7): checkpoints whose config would allocate gigabytes, YAML
alias bombs, huge meshes, an unreachable tracking server, and what a job's local Ray listens on.

Each refusal is checked to come before the work it guards: the checkpoint's model is never built off
the meta device, the bomb is refused as it is composed, the mesh before its first window, the server
within seconds. Everything here is tiny and fast except the Ray listeners (a real local Ray: slow).
"""

from __future__ import annotations

import http.server
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import pytest
import torch
from test_animate import animate_main, make_checkpoint, write_driver

from aniformer import animate, checkpoint
from aniformer.cli.args import apply_overrides, load_config
from aniformer.cli.exits import run
from aniformer.errors import UserError
from aniformer.model import AniFormer, AniFormerConfig
from pipeline import tracking

ROOT = Path(__file__).resolve().parents[1]
TINY = ROOT / "configs" / "tiny.yaml"


def one_line_error(capsys, call) -> str:
    """The message of `call` under `cli.run`: exit status 2 and one line on stderr."""
    with pytest.raises(SystemExit) as exit_:
        run(call)
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("error: "), err
    return err


# ------------------------------------------------------------------ checkpoints: sized from the config


def edited_checkpoint(path: Path, edit) -> Path:
    """make_checkpoint's tiny model, its saved state changed by `edit(state)`."""
    make_checkpoint(path)
    state = torch.load(path, weights_only=True)
    edit(state)
    torch.save(state, path)
    return path


@pytest.fixture
def only_meta_builds(monkeypatch):
    """`build_model` that fails the test when a model would be built off the meta device, i.e. with
    its weights allocated (3.8 GB for channels [8192, 8192]) before the checks ran."""
    real = checkpoint.build_model

    def build(config):
        assert torch.get_default_device().type == "meta", "the model was built before its config was checked"
        return real(config)

    monkeypatch.setattr(checkpoint, "build_model", build)


def test_a_config_larger_than_its_state_dict_is_refused_before_the_model_is_built(tmp_path, only_meta_builds):
    path = edited_checkpoint(tmp_path / "wide.pt", lambda s: s["config"]["model"].update(channels=[8192, 8192]))
    assert path.stat().st_size < 300_000
    start = time.perf_counter()
    with pytest.raises(UserError, match=r"describes 873,\d{3},\d{3} parameters, the file holds 2,564"):
        checkpoint.model_from_checkpoint(path)
    assert time.perf_counter() - start < 5


def test_a_config_beyond_any_sane_model_is_refused_by_its_parameter_count(tmp_path, only_meta_builds):
    path = edited_checkpoint(tmp_path / "huge.pt", lambda s: s["config"]["model"].update(channels=[65536, 65536]))
    with pytest.raises(UserError, match=r"a model of 55,\d{3},\d{3},\d{3} parameters \(208.0 GiB\); refusing more than"):
        checkpoint.model_from_checkpoint(path)


@pytest.mark.parametrize("config, words", [("model: {channels: [8]}", "config is a str, not a mapping"),
                                           ({"model": ["aniformer"]}, "model config is a list, not a mapping")])
def test_a_config_that_is_not_a_mapping_is_one_line(tmp_path, capsys, config, words):
    path = edited_checkpoint(tmp_path / "bad.pt", lambda s: s.update(config=config))
    assert words in one_line_error(capsys, lambda argv: checkpoint.model_from_checkpoint(path))


@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_non_finite_weights_are_refused_at_load(tmp_path, value):
    def poison(state):
        state["model"]["to_xyz.weight"][0, 0] = value

    path = edited_checkpoint(tmp_path / "diverged.pt", poison)
    with pytest.raises(UserError, match=r"not finite \(1 NaN or infinite values in to_xyz.weight\)"):
        checkpoint.model_from_checkpoint(path)


def test_the_animate_job_refuses_non_finite_weights_in_one_line(tmp_path, capsys):
    path = edited_checkpoint(tmp_path / "diverged.pt", lambda s: s["model"]["to_xyz.bias"].fill_(float("nan")))
    target = write_driver(tmp_path / "driving", frames=3) / "frame_0.obj"
    err = one_line_error(capsys, lambda argv: animate_main(["--checkpoint", path, "--target", target, "--driving",
                                                            tmp_path / "driving", "--out", tmp_path / "anim"]))
    assert "weights are not finite" in err and not (tmp_path / "anim").exists()


def test_intact_checkpoints_still_load(tmp_path):
    model, _ = checkpoint.model_from_checkpoint(make_checkpoint(tmp_path / "ok.pt"))
    assert isinstance(model, AniFormer)
    shipped, _ = checkpoint.model_from_checkpoint(checkpoint.PRETRAINED)
    assert sum(p.numel() for p in shipped.parameters()) == 46_629


# ------------------------------------------------------------------------------ YAML alias bombs


def laughs(levels: int = 9) -> str:
    """A billion-laughs list: level k holds ten aliases of level k - 1, 10^levels ints in all."""
    rows = ["  - &l0 [1, 2, 3, 4, 5, 6, 7, 8, 9, 10]"]
    rows += [f"  - &l{k} [{', '.join([f'*l{k - 1}'] * 10)}]" for k in range(1, levels)]
    return "\n".join(rows)


def test_an_alias_bomb_in_a_real_key_is_refused_fast(tmp_path, capsys, job_main):
    text = TINY.read_text()
    assert "  milestones: [100]\n" in text
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text(text.replace("  milestones: [100]\n", f"  milestones:\n{laughs()}\n"))
    assert bomb.stat().st_size < 5_000
    start = time.perf_counter()
    with pytest.raises(UserError, match="aliases expand to more than 100,000 nodes"):
        load_config(bomb)
    assert time.perf_counter() - start < 2
    err = one_line_error(capsys, lambda argv: job_main("train")(["--config", str(bomb), "--out", str(tmp_path / "o")]))
    assert "bomb.yaml: YAML aliases expand" in err


def test_an_alias_bomb_in_an_override_is_refused():
    with pytest.raises(UserError, match="override train.milestones: YAML aliases expand"):
        apply_overrides({}, [f"train.milestones=[{laughs().replace('  - ', '').replace(chr(10), ', ')}]"])


def test_a_recursive_alias_is_refused(tmp_path):
    path = tmp_path / "loop.yaml"
    path.write_text("train:\n  milestones: &loop [1, *loop]\n")
    with pytest.raises(UserError, match="alias refers to the node that contains it"):
        load_config(path)


def test_anchors_of_an_ordinary_size_still_work():
    config = load_config(ROOT / "configs" / "seeds.yaml")  # names NPT's override once, with an anchor
    runs = json.dumps(config)
    assert runs.count("model={name: npt") == 5


# ---------------------------------------------------------------------------------- huge meshes


@pytest.fixture
def slow_device(monkeypatch):
    """A device measured at 1 GFLOP/s, whatever this machine does."""
    monkeypatch.setattr(animate, "_MATMUL_RATES", {"cpu": 1e9})


def tiny_model() -> AniFormer:
    return AniFormer(AniFormerConfig(channels=(16,), extractor_channels=(8, 16), heads=2, window=3))


def test_a_huge_mesh_is_refused_with_an_estimate_and_a_pointer_to_decimation(slow_device):
    model = tiny_model()
    with pytest.raises(UserError) as refused:
        animate.check_inference_time(model, 28, (163_842, 163_842), "cpu")
    flops, message = 28 * model.forward_flops(163_842, 163_842), str(refused.value)
    assert f"at least ~{flops / 1e9 / 60:,.0f} min on cpu ({flops / 1e12:,.1f} TFLOP at the measured 1 GFLOP/s" in message
    assert "simplify_quadric_decimation" in message and "--force" in message


def test_force_runs_a_huge_mesh_with_a_warning_and_mid_sized_ones_only_warn(slow_device, capsys):
    model = tiny_model()
    assert animate.check_inference_time(model, 28, (163_842, 163_842), "cpu", force=True) > animate.REFUSE_SECONDS
    assert capsys.readouterr().err.startswith("warning: 28 windows of 163,842 driving and 163,842 target vertices")
    seconds = animate.check_inference_time(model, 28, (20_000, 20_000), "cpu")
    assert animate.WARN_SECONDS < seconds < animate.REFUSE_SECONDS and "warning:" in capsys.readouterr().err


def test_small_meshes_are_not_timed(monkeypatch, capsys):
    monkeypatch.setattr(animate, "matmul_flops_per_second", lambda device: pytest.fail("timed a small mesh"))
    assert animate.check_inference_time(tiny_model(), 28, (6_890, 6_890), "cpu") is None
    assert capsys.readouterr().err == ""


def test_the_matmul_rate_is_measured():
    rate = animate.matmul_flops_per_second("cpu")
    assert 1e8 < rate < 1e14 and animate.matmul_flops_per_second("cpu") == rate  # measured once


def test_the_animate_job_refuses_before_its_first_window(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(animate, "_MATMUL_RATES", {"cpu": 1.0})  # 1 FLOP/s: any mesh is huge
    monkeypatch.setattr(animate, "MIN_CHECKED_FLOPS", 0)
    driving = write_driver(tmp_path / "driving", frames=4)
    ckpt = make_checkpoint(tmp_path / "best.pt")
    argv = ["--checkpoint", ckpt, "--target", driving / "frame_0.obj", "--driving", driving, "--out", tmp_path / "anim",
            "--device", "cpu", "--no-progress"]
    err = one_line_error(capsys, lambda a: animate_main(argv))
    assert "2 windows of 162 driving and 162 target vertices" in err and "decimate the target" in err
    assert not (tmp_path / "anim").exists()


# ------------------------------------------------------------------------- unreachable tracking


@pytest.fixture
def fresh_probe(monkeypatch):
    monkeypatch.setattr(tracking, "_READY", set())


def test_a_tracking_server_that_refuses_connections_fails_in_one_line(tmp_path, monkeypatch, fresh_probe, capsys,
                                                                       free_ports):
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"http://127.0.0.1:{free_ports(1)[0]}")
    start = time.perf_counter()
    from pipeline.registry import resolve_checkpoint

    err = one_line_error(capsys, lambda argv: resolve_checkpoint("0123456789abcdef" * 2, tmp_path))
    assert "does not answer ([Errno 111] Connection refused)" in err
    with pytest.raises(UserError, match="does not answer"):
        tracking.start_job_run("job", {"a": 1}, out=tmp_path / "out")
    assert time.perf_counter() - start < 3


def test_a_tracking_server_that_never_answers_fails_within_the_probe_timeout(tmp_path, monkeypatch, fresh_probe):
    silent = socket.socket()
    silent.bind(("127.0.0.1", 0))
    silent.listen()  # accepts (the kernel does) and never says a word
    monkeypatch.setattr(tracking, "PROBE_TIMEOUT_S", 1)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"http://127.0.0.1:{silent.getsockname()[1]}")
    start = time.perf_counter()
    try:
        with pytest.raises(UserError, match="does not answer .*timed out"):
            tracking.start_job_run("job", {"a": 1}, out=tmp_path / "out")
    finally:
        silent.close()
    assert time.perf_counter() - start < 4


class Unauthorized(http.server.BaseHTTPRequestHandler):
    def do_GET(self):
        self.send_response(401)
        self.end_headers()

    def log_message(self, *args):
        pass


def test_a_server_that_answers_passes_the_probe_once(fresh_probe):
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Unauthorized)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    uri = f"http://127.0.0.1:{server.server_port}"
    try:
        tracking.require_reachable(uri)  # 401 behind authentication: it is there
    finally:
        server.shutdown()
        server.server_close()
    tracking.require_reachable(uri)  # reached before: not probed again (the server is gone now)


# ------------------------------------------------------------------------------ root causes


def test_the_root_cause_walks_every_kind_of_wrapper_and_stops_where_the_chain_is_cut():
    """One walker (aniformer.errors.root_cause) for the one-line errors of the tracking probe, Ray's start
    and a failed training: each wrapper those libraries put around the first error, and Python's own chains."""
    from aniformer.errors import root_cause

    class Wrapper(Exception):
        def __init__(self, **links):
            super().__init__("wrapper")
            self.__dict__.update(links)

    first, second = OSError(111, "Connection refused"), ValueError("rank 1")
    implicit = RuntimeError("raised while handling the first")  # requests' ConnectionError around urllib3's
    implicit.__context__ = first
    cut = RuntimeError("raised from None")
    cut.__context__, cut.__suppress_context__ = first, True

    assert root_cause(Wrapper(worker_failures={1: second, 0: first})) is first  # Ray Train: the lowest failed rank
    assert root_cause(Wrapper(controller_failure=Wrapper(cause=first))) is first  # its controller; a task error
    assert root_cause(Wrapper(reason=first)) is first  # urllib3's MaxRetryError
    assert root_cause(implicit) is first
    assert root_cause(cut) is cut  # `from None`: its own message is the whole story
    assert root_cause(Wrapper(cause="a string", reason=None)).args == ("wrapper",)  # not exceptions: no links
    loop = Wrapper()
    loop.__cause__ = Wrapper(cause=loop)
    assert root_cause(loop) in (loop, loop.__cause__)  # a cycle ends the walk


# ------------------------------------------------------------------------------ Ray's listeners

LISTENERS = """
import json, ray, psutil
from pipeline.cluster import connect
connect()
me = psutil.Process()
pids = {me.pid} | {p.pid for p in me.children(recursive=True)}
found = [(c.laddr.ip, c.laddr.port, psutil.Process(c.pid).name()) for c in psutil.net_connections(kind="inet")
         if c.status == psutil.CONN_LISTEN and c.pid in pids]
print(json.dumps({"listeners": found, "metrics_port": ray.nodes()[0]["MetricsExportPort"]}))
ray.shutdown()
"""


@pytest.mark.slow
def test_a_jobs_local_ray_listens_on_localhost_only():
    """pipeline.cluster.connect() without RAY_ADDRESS, in a process of its own: every TCP socket its
    Ray processes listen on (GCS, raylet, workers, dashboard, agents, Prometheus exporters)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}
    env["RAY_TMPDIR"] = tempfile.mkdtemp(prefix="ray", dir="/tmp")
    try:
        done = subprocess.run([sys.executable, "-c", LISTENERS], cwd=ROOT, env=env, capture_output=True, text=True,
                              timeout=240)
    finally:
        shutil.rmtree(env["RAY_TMPDIR"], ignore_errors=True)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "RAY_AUTH_MODE=disabled to opt out" not in done.stderr  # token auth is our default, not Ray's notice
    report = json.loads(done.stdout.strip().splitlines()[-1])
    listeners = report["listeners"]
    names = {name for _, _, name in listeners}
    assert {"gcs_server", "raylet", "ray::DashboardAgent"} <= names, listeners
    assert report["metrics_port"] in {port for _, port, _ in listeners}  # the node's Prometheus exporter
    outside = [entry for entry in listeners if entry[0] not in ("127.0.0.1", "::ffff:127.0.0.1", "::1")]
    assert not outside, f"listening beyond this machine: {outside}"


JOB_LISTENERS = """
import importlib, json, sys, threading, time, ray, psutil
found, stop = set(), threading.Event()

def watch():
    me = psutil.Process()
    while not stop.is_set():
        pids = {me.pid} | {p.pid for p in me.children(recursive=True)}
        for c in psutil.net_connections(kind="inet"):
            if c.status == psutil.CONN_LISTEN and c.pid in pids:
                try:
                    found.add((c.laddr.ip, c.laddr.port, psutil.Process(c.pid).name()))
                except psutil.Error:
                    pass
        time.sleep(0.2)

threading.Thread(target=watch, daemon=True).start()
importlib.import_module(f"jobs.{sys.argv[1]}").main(sys.argv[2:])
stop.set()
print(json.dumps(sorted(found)))
"""


def job_listeners(job: str, args: list[str], tmp_path: Path) -> list[tuple[str, int, str]]:
    """Every (address, port, process) the job and its own local Ray listened on while it ran (sampled every
    0.2 s), the job run as a user runs it: no RAY_ADDRESS, its own Ray temp dir and MLflow store."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}
    env |= {"RAY_TMPDIR": tempfile.mkdtemp(prefix="ray", dir="/tmp"), "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'm.db'}"}
    try:
        done = subprocess.run([sys.executable, "-c", JOB_LISTENERS, job, *args], cwd=ROOT, env=env, capture_output=True,
                              text=True, timeout=600)
    finally:
        shutil.rmtree(env["RAY_TMPDIR"], ignore_errors=True)
    assert done.returncode == 0, done.stderr[-3000:]
    return [tuple(entry) for entry in json.loads(done.stdout.strip().splitlines()[-1])]


def beyond_this_machine(listeners: list) -> list:
    return [entry for entry in listeners if entry[0] not in ("127.0.0.1", "::ffff:127.0.0.1", "::1")]


# A training of one epoch on 16 pairs made on the fly: no bank to generate.
STREAM = ["data.source=stream", "data.shuffle=none", "data.pairs_per_epoch=16", "data.eval_pairs=4", "train.epochs=1",
          "model.output=transfer"]


@pytest.mark.slow
def test_a_local_ddp_training_listens_on_localhost_only(tmp_path):
    """jobs/train.py on its own local Ray with two DDP workers: every socket any of its processes listened on
    while it trained. torch's rendezvous store listens on every interface; the job meets its workers at a
    file store instead (pipeline/ddp.py), and gloo's sockets are on the loopback interface."""
    listeners = job_listeners("train", ["--config", str(TINY), "--out", str(tmp_path / "out"), "--no-register",
                                        "--no-progress", *STREAM, "train.workers=2", "train.cpus_per_worker=0.5"], tmp_path)
    assert any(name.startswith("ray::RayTrainWorker") for _, _, name in listeners), listeners
    assert not beyond_this_machine(listeners), f"listening beyond this machine: {beyond_this_machine(listeners)}"


def retarget_args(tmp_path: Path, job_main) -> list[str]:
    """One Anny target x one 4-frame clip (the shipped model's topology: nothing to register)."""
    run(job_main("export_meshes"), ["--stream", "notoes_collapse3pc", "--frames", "4", "--out", str(tmp_path / "walk")])
    (tmp_path / "targets").mkdir()
    shutil.copy(tmp_path / "walk" / "target.obj", tmp_path / "targets" / "anny.obj")
    (tmp_path / "clips").mkdir()
    shutil.move(tmp_path / "walk" / "driving", tmp_path / "clips" / "walk")
    return ["--targets", str(tmp_path / "targets"), "--clips", str(tmp_path / "clips"), "--out", str(tmp_path / "lib"),
            "--no-progress"]


# One trial of one epoch on 16 streamed pairs: the sweep's Tune driver, trial actor and trainer, all on its own Ray.
SWEEP = ["--config", str(ROOT / "configs" / "sweep_tiny.yaml"), *STREAM, "sweep.num_samples=1", "sweep.window=[2, 3]"]


WORKER = {"sweep": "ray::RayTrainWorker", "retarget": "ray::Animator"}  # a trial's trainer; the model's actor


@pytest.mark.slow
@pytest.mark.parametrize("job", ["sweep", "retarget"])
def test_the_sweep_and_retarget_jobs_local_ray_listen_on_localhost_only(job, tmp_path, job_main):
    """jobs/sweep.py and jobs/retarget.py as a user runs them, each on its own local Ray: every socket of their
    process trees while they ran. (evaluate and animate start no Ray and open no listening socket.)"""
    args = [*SWEEP, "--out", str(tmp_path / "sweep")] if job == "sweep" else retarget_args(tmp_path, job_main)
    listeners = job_listeners(job, args, tmp_path)
    names = {name for _, _, name in listeners}
    assert {"gcs_server", "raylet"} <= names, listeners  # its own Ray was watched, and its workers: named by
    # their task while one runs ("ray::Animator.animate"), by the actor's class only while idle
    assert any(name.startswith(WORKER[job]) for name in names), listeners
    assert not beyond_this_machine(listeners), f"listening beyond this machine: {beyond_this_machine(listeners)}"


# ------------------------------------------------------------------------------ a Ray that cannot be reached

def train_with_ray_address(tmp_path: Path, address: str) -> tuple[subprocess.CompletedProcess, float]:
    start = time.perf_counter()
    done = subprocess.run([sys.executable, str(ROOT / "jobs/train.py"), "--config", str(TINY), "--out",
                           str(tmp_path / "out"), "train.epochs=1"], cwd=tmp_path, capture_output=True,
                          text=True, timeout=240, env={**os.environ, "RAY_ADDRESS": address,
                                                       "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}"})
    return done, time.perf_counter() - start


def assert_refused_in_one_line(done: subprocess.CompletedProcess, elapsed: float, message: str, tmp_path: Path):
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2 and len(lines) == 1 and lines[0].startswith(message), done.stderr[-3000:]
    assert not done.stdout.strip(), done.stdout[-3000:]
    assert elapsed < 120, f"{elapsed:.0f} s"  # imports on a loaded machine; the probes give up in 5 s each
    assert not (tmp_path / "out" / ".lock").exists()


@pytest.mark.parametrize(("address", "message"), [
    ("127.0.0.1:1", "error: RAY_ADDRESS 127.0.0.1:1: no Ray cluster answers at "),
    ("127.0.0.1:notaport", "error: RAY_ADDRESS '127.0.0.1:notaport': the port 'notaport' is not a number in 1-65535"),
], ids=["nothing-listens", "bad-port"])
def test_a_ray_address_that_cannot_be_reached_is_one_line_and_exit_2(tmp_path, address, message):
    """Before, `ray.init` retried the GCS connection for minutes and ended in a 20-line traceback."""
    assert_refused_in_one_line(*train_with_ray_address(tmp_path, address), message, tmp_path)


@pytest.mark.parametrize("listener", ["web-server", "silent"])
def test_a_ray_address_where_something_else_listens_is_refused_by_the_probe(listener):
    """A port that accepts TCP but is not Ray's GCS (a web server, or one that never answers): before,
    `ray.init` retried for 14 min. Bound where Ray dials: it replaces 127.0.0.1 by the node's address."""
    import ray

    from pipeline.cluster import probe_cluster

    host = ray.util.get_node_ip_address()
    if listener == "web-server":
        server = http.server.ThreadingHTTPServer((host, 0), Unauthorized)
        threading.Thread(target=server.serve_forever, daemon=True).start()
        port, close = server.server_port, lambda: (server.shutdown(), server.server_close())
    else:
        silent = socket.socket()
        silent.bind((host, 0))
        silent.listen()
        port, close = silent.getsockname()[1], silent.close
    try:
        with pytest.raises(UserError) as refused:
            probe_cluster(f"127.0.0.1:{port}")
    finally:
        close()
    assert str(refused.value).startswith(f"RAY_ADDRESS 127.0.0.1:{port}: something listens at {host}:{port} but "
                                         "it is not a Ray cluster's head (no gRPC handshake in 5 s)")


def test_a_local_ray_that_cannot_start_is_one_line_and_exit_2(tmp_path):
    """No RAY_ADDRESS, and a temp dir Ray cannot create (RAY_TMPDIR under a file): before, a traceback."""
    (tmp_path / "a-file").write_text("")
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}
    env["RAY_TMPDIR"] = str(tmp_path / "a-file" / "ray")
    done = subprocess.run([sys.executable, str(ROOT / "jobs/train.py"), "--config", str(TINY), "--out",
                           str(tmp_path / "out"), "train.epochs=1"], cwd=tmp_path, capture_output=True, text=True,
                          timeout=240, env={**env, "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}"})
    assert done.returncode == 2, done.stderr[-3000:]
    assert done.stderr.strip().splitlines() == [
        f"error: a local Ray instance could not start: [Errno 20] Not a directory: '{env['RAY_TMPDIR']}'"]
    assert not (tmp_path / "out" / ".lock").exists()


def test_a_local_ray_node_that_times_out_starting_is_one_line(monkeypatch):
    """What ray.init raised under a load average of 35 (bench/soak.py): a bare Exception, before a traceback.
    Its start-up timeout cannot be produced on demand, so ray.init raises it here."""
    import ray

    from aniformer.errors import UserError
    from pipeline import cluster

    def timed_out(**kwargs):
        raise Exception("The current node timed out during startup. This could happen because some of the Ray "
                        "processes failed to startup.")

    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    monkeypatch.setenv(cluster.API_SERVER_ENV, os.environ.get(cluster.API_SERVER_ENV, ""))  # connect sets it: restored after
    monkeypatch.setattr(ray, "is_initialized", lambda: False)
    monkeypatch.setattr(ray, "init", timed_out)
    with pytest.raises(UserError, match="^a local Ray instance could not start: The current node timed out"):
        cluster.connect()


def test_a_ray_clusters_head_passes_the_probe(ray_address):
    from pipeline.cluster import probe_cluster

    probe_cluster(ray_address)  # the session's real cluster: its GCS completes the handshake
