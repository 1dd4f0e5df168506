"""The layers of DESIGN.md hold: import-linter's contract in pyproject.toml, run over the whole tree."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

import grimp

from swimm.commands import COMMANDS

ROOT = Path(__file__).resolve().parents[2]
#: import-linter's command beside this interpreter: the project's virtual environment need not be on PATH.
LINT_IMPORTS = Path(sys.executable).with_name("lint-imports")


def test_each_layer_imports_only_the_layers_below_it() -> None:
    result = subprocess.run([str(LINT_IMPORTS), "--no-cache"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-2000:]
    assert "1 kept, 0 broken" in result.stdout


def test_the_import_check_sees_every_command() -> None:
    """Each command's loader imports its module where import-linter's graph (grimp) reads it: a command named by a
    string instead would escape the contract."""
    contract = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]
    imported = grimp.build_graph(*contract["root_packages"], cache_dir=None).find_modules_directly_imported_by(
        "swimm.commands"
    )
    for name, command in COMMANDS.items():
        assert command.load().run.__module__ in imported, name


def test_the_architecture_picture_draws_the_contract_s_layers() -> None:
    """docs/architecture.md's layer picture: every edge goes from a layer to the one below it in the contract,
    and every layer is drawn."""
    contract = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"][0]
    layers = [set(layer.split(" | ")) for layer in contract["layers"]]  # top first
    level = {package: index for index, layer in enumerate(layers) for package in layer}
    doc = (ROOT / "docs" / "architecture.md").read_text()
    picture = doc.split("```mermaid\nflowchart TB\n", 1)[1].split("```", 1)[0]
    edges = [line.strip() for line in picture.splitlines() if "-->" in line]
    drawn = set()
    for edge in edges:
        steps = [set(part.strip().split(" & ")) for part in edge.split("-->")]
        for upper, lower in zip(steps, steps[1:], strict=False):
            for a in upper:
                for b in lower:
                    assert level[b] == level[a] + 1, f"{a} --> {b} skips or climbs a layer"
                    drawn |= {a, b}
    assert drawn == set(level), f"not drawn: {set(level) - drawn}"
