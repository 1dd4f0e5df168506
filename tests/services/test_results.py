"""A result table's provenance written beside it (services.results.write_provenance_beside)."""

from __future__ import annotations

import json

import pandas as pd

from services.results import file_sha256, provenance, write_provenance_beside


def test_a_tables_provenance_lies_beside_it_and_a_growing_table_keeps_every_run(tmp_path) -> None:
    model = tmp_path / "model.pt"
    model.write_bytes(b"weights")
    table = tmp_path / "rows.csv"
    pd.DataFrame({"episode": [1]}).to_csv(table, index=False)
    first = write_provenance_beside(table, provenance({"cmvae": model}, seeds=[211]), append=True)
    assert first == tmp_path / "rows.csv.provenance.json"
    second = write_provenance_beside(table, provenance({"cmvae": model}, seeds=[113]), append=True)
    runs = json.loads(second.read_text())["runs"]
    assert [run["seeds"] for run in runs] == [[211], [113]]
    assert runs[0]["models"]["cmvae"] == {"path": str(model), "sha256": file_sha256(model)}
    assert runs[0]["git"]["commit"] and runs[0]["host"]["cores"] >= 1
    rewritten = json.loads(write_provenance_beside(table, provenance(seeds=[5])).read_text())
    assert rewritten["table"] == "rows.csv" and [run["seeds"] for run in rewritten["runs"]] == [[5]]
