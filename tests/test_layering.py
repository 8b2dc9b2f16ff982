"""The layering of docs/architecture.md, checked: import-linter's contracts in pyproject.toml ([tool.importlinter]).

`lint-imports` reads every module of aniformer/, pipeline/ and jobs/ (imports inside functions too) without
importing them, so this takes well under a second. The jobs' --help runs, which check what a job loads before
its arguments are read, take a fraction of a second each.
"""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# The same as `lint-imports --no-cache --no-logo` from the repository root, with this interpreter's import-linter
# (a dev extra); no cache directory is written into the checkout.
LINT_IMPORTS = "import sys; from importlinter.cli import lint_imports_command; sys.exit(lint_imports_command())"


def test_import_contracts_are_kept():
    done = subprocess.run([sys.executable, "-c", LINT_IMPORTS, "--no-cache", "--no-logo"],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    output = done.stdout + done.stderr
    assert done.returncode == 0, f"lint-imports failed (exit {done.returncode}):\n{output}"
    # every contract of pyproject.toml was checked and kept: none dropped from the run unnoticed
    contracts = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
    assert len(contracts) >= 5
    for contract in contracts:
        assert f"{contract['name']} KEPT" in output, f"{contract['name']!r} not reported kept:\n{output}"


# Every job's --help loads no heavy library (seconds of start-up each).
LIGHT_HELP_JOBS = ("ablate", "animate", "evaluate", "export_meshes", "generate_data", "retarget", "sweep", "train")
LOADED_AFTER = ("import runpy, sys; sys.argv = sys.argv[1:]\n"
                "try:\n    runpy.run_path(sys.argv[0], run_name='__main__')\nexcept SystemExit:\n    pass\n"
                "print('loaded:', *(m for m in ('torch', 'trimesh', 'ray', 'mlflow') if m in sys.modules))")


@pytest.mark.parametrize("job", LIGHT_HELP_JOBS)
def test_a_jobs_help_loads_no_heavy_library(job):
    done = subprocess.run([sys.executable, "-c", LOADED_AFTER, f"jobs/{job}.py", "--help"], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert "usage:" in done.stdout, done.stderr
    assert done.stdout.rsplit("loaded:", 1)[1].split() == [], f"--help of jobs/{job}.py loaded those"


@pytest.mark.parametrize("missing", ["--target", "--driving"])
def test_animate_refuses_a_missing_input_before_loading_torch(missing, tmp_path):
    """A mistyped path is answered at once (one line, exit 2), not after seconds of imports."""
    (tmp_path / "clip").mkdir()
    (tmp_path / "clip" / "frame_0000.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    given = {"--target": str(tmp_path / "clip" / "frame_0000.obj"), "--driving": str(tmp_path / "clip")}
    given[missing] = str(tmp_path / "nope.obj")
    argv = ["jobs/animate.py", *(item for flag in given for item in (flag, given[flag])), "--out", str(tmp_path / "out")]
    done = subprocess.run([sys.executable, "-c", LOADED_AFTER, *argv], cwd=ROOT, capture_output=True, text=True,
                          timeout=120)
    assert done.stderr.startswith("error: ") and "nope.obj: no such" in done.stderr, done.stderr
    assert done.stdout.rsplit("loaded:", 1)[1].split() == [] and not (tmp_path / "out").exists()
