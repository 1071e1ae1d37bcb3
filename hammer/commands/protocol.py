"""Commands of this package, added to the `hammer` CLI by `hammer.cli`.

  hammer protocol schema [--out FILE]    JSON Schema of every message

The protocol's benchmarks (`hammer bench transport`, `hammer bench codec`) are in `benchmarks/`.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer


def register(app: typer.Typer) -> None:
    """Add this package's commands to the top-level app."""
    protocol = typer.Typer(help="The wire protocol shared by every hammer role.", no_args_is_help=True)
    app.add_typer(protocol, name="protocol")

    @protocol.command("schema")
    def schema(
        out: Annotated[Path | None, typer.Option("--out", help="write to this file instead of stdout")] = None,
    ) -> None:
        """Print (or write) the JSON Schema of every message type, keyed by type tag."""
        from hammer.protocol.schemas import json_schemas

        text = json.dumps(json_schemas(), indent=2)
        if out is None:
            typer.echo(text)
        else:
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_text(text + "\n")
            typer.echo(f"wrote {out}")
