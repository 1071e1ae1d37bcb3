"""Commands of this package, added to the `hammer` CLI by `hammer.cli`.

  hammer protocol schema [--out FILE]    JSON Schema of every message
  hammer bench transport [--json FILE]   typed protocol vs raw Zenoh bytes: msgs/s and round trips
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer


def register(app: typer.Typer, bench: typer.Typer) -> None:
    """Add this package's commands to the top-level app and its `bench` group."""
    protocol = typer.Typer(help="The wire protocol shared by every hammer role.", no_args_is_help=True)
    app.add_typer(protocol, name="protocol")

    @protocol.command("schema")
    def schema(
        out: Annotated[Path | None, typer.Option("--out", help="write to this file instead of stdout")] = None,
    ) -> None:
        """Print (or write) the JSON Schema of every message type, keyed by type tag."""
        from protocol.schemas import json_schemas

        text = json.dumps(json_schemas(), indent=2)
        if out is None:
            typer.echo(text)
        else:
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_text(text + "\n")
            typer.echo(f"wrote {out}")

    @bench.command("transport")
    def transport(
        rounds: Annotated[int, typer.Option(min=10, help="round trips per payload and mode")] = 1000,
        flood: Annotated[int, typer.Option(min=100, help="messages per throughput burst")] = 5000,
        json_out: Annotated[Path | None, typer.Option("--json", help="also write the figures as JSON")] = None,
    ) -> None:
        """Messages/s and round-trip p50/p99 of typed messages vs raw bytes of the same size,
        over Zenoh on 127.0.0.1 to an echo peer in another (spawned) process."""
        from rich.console import Console
        from rich.table import Table

        from protocol.bench import bench_meta, rows_as_dicts, run_bench

        rows = run_bench(rounds=rounds, flood=flood)
        table = Table(title="hammer bench transport (typed protocol vs raw bytes, loopback, echo process)")
        for col in ("payload", "bytes", "enc us", "dec us", "typed msg/s", "raw msg/s", "ratio",
                    "typed rtt p50/p99 us", "raw rtt p50/p99 us", "rtt ratio"):
            table.add_column(col, justify="left" if col == "payload" else "right")
        for r in rows:
            table.add_row(
                r.payload, str(r.bytes), f"{r.encode_us:.1f}", f"{r.decode_us:.1f}",
                f"{r.typed_msgs_per_s:,.0f}", f"{r.raw_msgs_per_s:,.0f}", f"{r.rate_ratio:.2f}",
                f"{r.typed_rtt_p50_us:.0f} / {r.typed_rtt_p99_us:.0f}",
                f"{r.raw_rtt_p50_us:.0f} / {r.raw_rtt_p99_us:.0f}", f"{r.rtt_ratio:.2f}",
            )
        console = Console()
        if not console.is_terminal:
            console = Console(width=170)  # keep the table readable in logs and CI output
        console.print(table)
        if json_out is not None:
            json_out.parent.mkdir(parents=True, exist_ok=True)
            json_out.write_text(json.dumps({"meta": bench_meta(rounds, flood), "rows": rows_as_dicts(rows)},
                                           indent=2) + "\n")
            typer.echo(f"wrote {json_out}")
