"""One module per evaluation stage, each with ``run(ws: Workspace) -> dict`` (see evaluation/runner.py)."""
