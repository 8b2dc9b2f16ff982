"""cluster.yaml: valid for Ray's own cluster launcher, and secure as configured.

Validation uses what `ray up` itself runs before touching the cloud (`prepare_config`, which merges
the AWS defaults, then `validate_config`, Ray's JSON schema plus its consistency checks). The
security checks read the prepared config: what the nodes will actually run.
"""

from __future__ import annotations

import ast
import copy
import re
import shlex
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def raw() -> dict:
    return yaml.safe_load((ROOT / "cluster.yaml").read_text())


@pytest.fixture(scope="module")
def prepared(raw) -> dict:
    from ray.autoscaler._private.util import prepare_config, validate_config

    config = prepare_config(copy.deepcopy(raw))
    validate_config(config)
    return config


def pins() -> dict[str, str]:
    """Exact pins of pyproject.toml's dependencies ("name[extras]==version")."""
    text = (ROOT / "pyproject.toml").read_text()
    return {m.group(1).lower(): m.group(2) for m in re.finditer(r'"([A-Za-z0-9_.-]+)(?:\[[^\]]*\])?==([^"\s;]+)"', text)}


def env_file(commands: list[str]) -> dict[str, str]:
    """The variables written to ~/aniformer.env (the environment of every Ray process on the node)."""
    (cmd,) = [c for c in commands if c.rstrip().endswith("> ~/aniformer.env")]
    words = shlex.split(cmd[cmd.index("printf"):].rsplit(">", 1)[0])
    assert words[:2] == ["printf", "export %s\\n"]
    return dict(w.split("=", 1) for w in words[2:])


def ray_starts(commands: list[str]) -> list[str]:
    return [c for c in commands if "ray start" in c]


def flag(command: str, name: str) -> str | None:
    words = shlex.split(command.replace("&&", " ; "))
    for i, word in enumerate(words):
        if word == name:
            return words[i + 1]
        if word.startswith(name + "="):
            return word.split("=", 1)[1]
    return None


def test_ray_validates_the_cluster_config(prepared):
    types = prepared["available_node_types"]
    head = types[prepared["head_node_type"]]
    assert head["node_config"]["InstanceType"].startswith("m5") and not head["resources"].get("GPU")
    gpu = {t["node_config"]["InstanceType"]: t for name, t in types.items() if name != prepared["head_node_type"]}
    assert gpu["p3.2xlarge"]["resources"]["GPU"] == 1 and gpu["p3.8xlarge"]["resources"]["GPU"] == 4  # V100s
    for t in gpu.values():
        assert t["min_workers"] == 0 < t["max_workers"] <= prepared["max_workers"]


def test_only_ssh_is_open_to_the_outside(prepared):
    """Ray's AWS provider creates the security group from its defaults plus our IpPermissions:
    evaluate Ray's own rule builder (read from its source: importing it needs boto3) on our config."""
    import importlib.util

    tree = ast.parse(Path(importlib.util.find_spec("ray.autoscaler._private.aws.config").origin).read_text())
    wanted = {"_create_default_inbound_rules", "_create_default_intracluster_inbound_rules",
              "_create_default_ssh_inbound_rules"}
    namespace: dict = {"itertools": __import__("itertools")}
    exec(compile(ast.Module([n for n in tree.body if getattr(n, "name", None) in wanted], []), "aws_config", "exec"),
         namespace)
    assert wanted <= set(namespace), "Ray's AWS provider builds its security group differently now: recheck"
    extra = prepared["provider"]["security_group"]["IpPermissions"]
    rules = namespace["_create_default_inbound_rules"]({"sg-ray-aniformer"}, extra)
    for rule in rules:
        from_outside = any(rule.get(k) for k in ("IpRanges", "Ipv6Ranges", "PrefixListIds"))
        if from_outside:
            assert (rule["IpProtocol"], rule["FromPort"], rule["ToPort"]) == ("tcp", 22, 22), rule
        else:  # between the cluster's own nodes (its security group)
            assert [p["GroupId"] for p in rule["UserIdGroupPairs"]] == ["sg-ray-aniformer"], rule
    for node_type in prepared["available_node_types"].values():  # no group of our own that could open more
        assert not {"SecurityGroupIds", "NetworkInterfaces"} & set(node_type["node_config"])


def test_dashboard_and_job_api_listen_on_localhost_only(prepared):
    (head,) = ray_starts(prepared["head_start_ray_commands"])
    assert flag(head, "--dashboard-host") == "127.0.0.1" and flag(head, "--include-dashboard") == "true"
    everything = yaml.safe_dump(prepared)
    assert "0.0.0.0" not in everything and "--host ::" not in everything


def test_token_authentication_on_every_node(prepared, raw):
    head_env, worker_env = env_file(prepared["head_setup_commands"]), env_file(prepared["worker_setup_commands"])
    assert head_env["RAY_AUTH_MODE"] == "token" == worker_env["RAY_AUTH_MODE"]
    for commands in (prepared["head_start_ray_commands"], prepared["worker_start_ray_commands"]):
        assert all(c.startswith("source ~/aniformer.env &&") for c in ray_starts(commands))
    # The token comes from the user's ~/.ray/auth_token (file_mounts), never from this file.
    assert raw["file_mounts"]["/home/ubuntu/.ray/auth_token"] == "~/.ray/auth_token"
    assert "RAY_AUTH_TOKEN" not in (ROOT / "cluster.yaml").read_text()


def test_mlflow_server_on_the_private_ip_with_auth_and_jobs_log_there(prepared):
    (server,) = [c for c in prepared["head_start_ray_commands"] if "pipeline.mlflow_server" in c]
    head_env, worker_env = env_file(prepared["head_setup_commands"]), env_file(prepared["worker_setup_commands"])
    # Bound to one address, the head's private IP from the instance metadata (workers log into it).
    assert flag(server, "--host") == "$HEAD_IP" and "HEAD_IP=$(imds local-ipv4)" in " ".join(prepared["head_setup_commands"])
    assert "--allow-all-interfaces" not in server
    assert "--auth" in server and flag(server, "--password-file") == "/home/ubuntu/.ray/auth_token"
    port = flag(server, "--port")
    assert head_env["MLFLOW_TRACKING_URI"] == f"http://$HEAD_IP:{port}"
    assert worker_env["MLFLOW_TRACKING_URI"] == f"http://$RAY_HEAD_IP:{port}"
    for env in (head_env, worker_env):
        assert env["MLFLOW_TRACKING_USERNAME"] == "admin"
        assert env["MLFLOW_TRACKING_PASSWORD"] == "$(cat $HOME/.ray/auth_token)"
    # Durable: backed up to S3, artifacts in S3 (the default of pipeline.mlflow_server with an s3:// backup).
    assert flag(server, "--backup") == "$ANIFORMER_MLFLOW_BACKUP" and head_env["ANIFORMER_MLFLOW_BACKUP"].startswith("s3://")


def test_every_node_installs_this_project_with_its_pins(prepared, raw):
    assert raw["file_mounts"]["/home/ubuntu/aniformer"] == "."
    assert ".gitignore" in raw["rsync_filter"]  # not the local .venv, runs, databases
    setup = " ".join(prepared["setup_commands"])
    versions = pins()
    assert f"torch=={versions['torch']}" in setup and "pip install -q -e ~/aniformer" in setup
    assert "sm_70" in setup  # the torch build is checked to have V100 kernels
    assert f"mlflow[auth]=={versions['mlflow']}" in " ".join(prepared["head_setup_commands"])
    for name, node_type in prepared["available_node_types"].items():
        if node_type["resources"].get("GPU"):
            assert any("580" in c for c in node_type["initialization_commands"]), name  # a Volta-capable driver
    assert "mount -t nfs4 $RAY_HEAD_IP:/mnt/shared /mnt/shared" in " ".join(prepared["worker_setup_commands"])
