"""The layering of docs/architecture.md, checked: import-linter's contracts in pyproject.toml ([tool.importlinter]).

`lint-imports` reads every module of aniformer/, pipeline/ and jobs/ (imports inside functions too) without
importing them, so this takes well under a second.
"""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

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
