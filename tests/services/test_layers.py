"""The layers of DESIGN.md hold: import-linter's contract in pyproject.toml, run over the whole tree."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
#: import-linter's command beside this interpreter: the project's virtual environment need not be on PATH.
LINT_IMPORTS = Path(sys.executable).with_name("lint-imports")


def test_each_layer_imports_only_the_layers_below_it() -> None:
    result = subprocess.run([str(LINT_IMPORTS), "--no-cache"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-2000:]
    assert "1 kept, 0 broken" in result.stdout
