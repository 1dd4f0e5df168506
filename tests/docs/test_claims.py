"""Every figure swimm claims in README.md's "What it reaches" table is held by a committed result file it links to.

The rule the table follows, checked here on the swimm column (the first column describes each row's setup and the
paper's column quotes SWiMM 2.0: neither is a swimm result, neither is checked):

- a numeral is a claim, and a claim is the text of a markdown link ``[2570](docs/eval_report/general/suite.csv)``
  whose target is a result file a command wrote: a ``.json`` or ``.csv`` under docs/ (prose such as docs/learner.md
  is context, never a source);
- the linked file must hold a number that rounds to the quoted one at the quoted precision: ``2570`` accepts
  2569.66, ``0.741`` accepts 0.7409, ``2.53e3`` accepts 2530.9 (tens, as the mantissa's digits say), ``-1923``
  accepts -1923.10; a thousands comma (``2,570``) is read as 2570;
- the one exemption is a setting's size, not a result: a whole number followed by one of ``EXEMPT_UNITS``
  ("3 episodes", "3000 steps", "30000 frames", "160 ms", "25 Hz"); anything else numeric outside a link fails;
- a speed figure (a cell saying steps/s) states the host's in-process World steps/s with a linked figure.
"""

from __future__ import annotations

import re
from decimal import Decimal
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
SECTION = "## What it reaches"
#: Result files a claim may point at: what commands write under docs/, never prose.
RESULT_SUFFIXES = (".json", ".csv")
#: Words that make a whole number a setting's size rather than a result: "3 episodes of 3000 steps", "30000 frames",
#: and an evaluation's delay or control rate, "actions 160 ms late", "at 25 Hz". Only whole numbers: a measured
#: time or count quoted with decimals, or followed by any other word ("3 minutes", "11 of 20"), is a claim.
EXEMPT_UNITS = ("episodes", "episode", "steps", "seeds", "frames", "ms", "Hz")

#: A numeral as the README quotes it: optional sign, digits with optional thousands commas, decimals, exponent.
#: Digits inside a name (td3, cmvae_v2) are not a figure; digits before letters are ("5x smoother", "12k").
QUOTED = re.compile(r"(?<![\w.])[-\u2212]?(?:\d{1,3}(?:,\d{3})+(?:\.\d+)?|\d+(?:\.\d+)?(?:e[-+]?\d+)?)")
#: A number as a result file stores it.
STORED = re.compile(r"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")
LINK = re.compile(r"\[([^\]]*)\]\(([^)\s]+)\)")
EXEMPT = re.compile(r"(?<![\w.])\d+ (?:" + "|".join(EXEMPT_UNITS) + r")\b")


def _decimal(text: str) -> Decimal:
    return Decimal(text.replace(",", "").replace("\u2212", "-"))


def rounds_to(stored: str, quoted: str) -> bool:
    """Whether a stored number, rounded at the quoted number's last digit, is the quoted number (ties either way)."""
    want = _decimal(quoted)
    half_unit = Decimal(5).scaleb(want.as_tuple().exponent - 1)
    try:
        return abs(Decimal(stored) - want) <= half_unit
    except ArithmeticError:  # not a number, or one out of range (a hash's digits read as 514e3274009)
        return False


def table_rows(markdown: str, column: str = "swimm") -> list[tuple[str, str]]:
    """(first cell, the named column's cell) of every body row of the table under SECTION."""
    body = markdown.split(SECTION, 1)[1]
    body = body.split("\n## ", 1)[0]
    lines = [line for line in body.splitlines() if line.startswith("|")]
    assert len(lines) > 2, f"no table under {SECTION!r}"
    header = [cell.strip() for cell in lines[0].strip("|").split("|")]
    index = header.index(column)
    rows = []
    for line in lines[2:]:
        cells = [cell.strip() for cell in line.strip("|").split("|")]
        rows.append((cells[0], cells[index]))
    return rows


def claim_problems(markdown: str, root: Path = ROOT) -> list[str]:
    """Every figure in the swimm column that is unlinked, linked to a non-result file, or not held by its file."""
    problems: list[str] = []
    numbers_in: dict[Path, list[str]] = {}
    for row, cell in table_rows(markdown):
        where = row[:60]
        for text, target in LINK.findall(cell):
            quoted = QUOTED.findall(text)
            if not quoted:
                continue
            path = (root / target.split("#", 1)[0]).resolve()
            if not (path.is_relative_to(root / "docs") and path.suffix in RESULT_SUFFIXES and path.is_file()):
                problems.append(f"{where}: [{text}] points at {target}, not a committed result file under docs/")
                continue
            if path not in numbers_in:
                numbers_in[path] = STORED.findall(path.read_text())
            for number in quoted:
                if not any(rounds_to(stored, number) for stored in numbers_in[path]):
                    problems.append(f"{where}: {number} is not in {target}")
        unlinked = EXEMPT.sub(" ", LINK.sub(" ", cell))
        problems.extend(f"{where}: {number} carries no link" for number in QUOTED.findall(unlinked))
    return problems


def speed_problems(markdown: str) -> list[str]:
    """Swimm cells that give a figure beside steps/s without the host's in-process World steps/s as a linked figure."""
    world = re.compile(r"\[[^\]]*\d[^\]]*\]\([^)]+\) in-process World steps/s")
    return [
        row[:60]
        for row, cell in table_rows(markdown)
        if "steps/s" in cell and QUOTED.search(cell) and not world.search(cell)
    ]


def test_every_figure_swimm_claims_in_the_readme_is_held_by_the_committed_file_it_links() -> None:
    markdown = README.read_text()
    assert len(table_rows(markdown)) >= 5
    assert claim_problems(markdown) == []


def test_every_speed_figure_states_the_hosts_in_process_world_steps_per_s() -> None:
    assert speed_problems(README.read_text()) == []


def _table(cell: str) -> str:
    return (
        f"{SECTION}\n\n| | swimm | the paper |\n| --- | --- | --- |\n| a row | {cell} | 2.40e3 unlinked |\n\n## Next\n"
    )


#: A real committed file and a figure it holds: docs/eval_report/general/suite.csv's clean return is 2569.66.
SUITE = "docs/eval_report/general/suite.csv"


@pytest.mark.parametrize(
    "cell",
    [
        f"clean [2570]({SUITE})",
        f"clean [2.57e3]({SUITE})",
        f"clean [2,570]({SUITE}), 3 episodes of 3000 steps",
        f"low sun [-1923]({SUITE})",
        f"clean [2569.66]({SUITE})",
    ],
)
def test_a_figure_its_file_holds_passes(cell: str) -> None:
    assert claim_problems(_table(cell)) == []


@pytest.mark.parametrize(
    "cell",
    [
        f"clean [2571]({SUITE})",  # one off at the quoted precision
        f"clean [2569.8]({SUITE})",  # the file holds 2569.66..., 2569.7 at one decimal
        f"clean [2.58e3]({SUITE})",
        f"low sun [1923]({SUITE})",  # the sign matters
        "clean [2570](docs/learner.md)",  # prose is not a source
        "clean [2570](docs/eval_report/general/missing.csv)",
        f"clean [2570]({SUITE}), murky 2537",  # a figure with no link
        "lost in 11 of 20",  # counts are claims too, unless they are a setting's size
        "3 minutes",
        "p50 1.5 ms",  # a measured time, not a setting
        "5x smoother",
        "after 12k steps",
    ],
    ids=[
        "off-by-one",
        "decimals",
        "exponent",
        "sign",
        "prose",
        "missing",
        "unlinked",
        "count",
        "time",
        "measured-ms",
        "times",
        "thousands",
    ],
)
def test_a_figure_its_file_does_not_hold_or_that_has_no_file_fails(cell: str) -> None:
    assert claim_problems(_table(cell)) != [], cell


def test_a_speed_figure_without_the_hosts_world_steps_per_s_fails() -> None:
    bench = "docs/bench/world/bench-sim.json"
    assert speed_problems(_table(f"distributed / in-process [0.351]({bench}) steps/s")) != []
    assert speed_problems(_table(f"[0.351]({bench}) of [2063.3]({bench}) in-process World steps/s")) == []
