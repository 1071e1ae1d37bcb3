"""Commands of this package, added to the `hammer` CLI by `hammer.cli`."""

from __future__ import annotations

import typer


def register(app: typer.Typer, bench: typer.Typer) -> None:
    """Add this package's commands to the top-level app and its `bench` group."""
