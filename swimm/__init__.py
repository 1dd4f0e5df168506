"""The `swimm` command line, on top of every service it starts: each command is registered in
:mod:`swimm.commands` by the imports of its loader, so the import check sees it (docs/architecture.md)."""
