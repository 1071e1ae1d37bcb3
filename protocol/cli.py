"""Commands of this package, added to the `hammer` CLI by `hammer.cli`.

  hammer protocol schema [--out FILE]    JSON Schema of every message
  hammer bench transport [--json FILE]   typed protocol vs raw Zenoh bytes: msgs/s and round trips
  hammer bench codec [--cold] [--json F]  build/encode/decode us per message: fast path vs pydantic
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
        from rich.table import Table

        from hammer.console import table_console
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
        console = table_console()
        console.print(table)
        if json_out is not None:
            json_out.parent.mkdir(parents=True, exist_ok=True)
            json_out.write_text(json.dumps({"meta": bench_meta(rounds, flood), "rows": rows_as_dicts(rows)},
                                           indent=2) + "\n")
            typer.echo(f"wrote {json_out}")

    @bench.command("codec")
    def codec(
        k: Annotated[int, typer.Option(min=1, help="env copies per message (K)")] = 32,
        number: Annotated[int, typer.Option(min=1, help="calls per timing (--cold: calls per figure)")] = 500,
        repeat: Annotated[int, typer.Option(min=1, help="timings per figure (the best is kept)")] = 7,
        cold: Annotated[bool, typer.Option("--cold", help="time single calls with cold caches (median CPU "
                                                           "time; --number calls each), as a woken-up role")] = False,
        json_out: Annotated[Path | None, typer.Option("--json", help="also write the figures as JSON")] = None,
    ) -> None:
        """Microseconds to build (validate), encode and decode (validate) each message of the
        control loop, fast path vs the pydantic reference measured in the same run."""
        import os
        import platform

        from rich.table import Table

        from hammer.console import table_console
        from protocol.bench import codec_bench, codec_rows_as_dicts, role_costs

        sizes = ((3, 18, 4), (5, 30, 8))
        rows = codec_bench(k=k, sizes=sizes, number=number, repeat=repeat, cold=cold)
        load = os.getloadavg()
        console = table_console()
        regime = "cache-cold single calls, median CPU time" if cold else "hot loop, best wall time"
        table = Table(title=f"hammer bench codec (us per message, {regime}; ref = pydantic, fast = fast path; "
                            f"load {load[0]:.2f})")
        for col in ("payload", "bytes", "build ref/fast", "encode ref/fast", "decode ref/fast", "total ref/fast",
                    "speedup"):
            table.add_column(col, justify="left" if col == "payload" else "right")
        for r in rows:
            table.add_row(r.payload, str(r.bytes), f"{r.build_ref_us:.1f} / {r.build_fast_us:.1f}",
                          f"{r.encode_ref_us:.1f} / {r.encode_fast_us:.1f}",
                          f"{r.decode_ref_us:.1f} / {r.decode_fast_us:.1f}",
                          f"{r.total_ref_us:.1f} / {r.total_fast_us:.1f}", f"{r.speedup:.2f}x")
        console.print(table)
        roles = Table(title="codec time per vector step and role (us)"
                      + (", upper bound: a role pays cold caches once per wake-up, not per call" if cold else ""))
        for col in ("N", "role", "reference", "fast", "speedup"):
            roles.add_column(col, justify="left" if col == "role" else "right")
        per_role = {}
        for n, _, _ in sizes:
            per_role[n] = role_costs(rows, k, n)
            for role, (ref, fast) in per_role[n].items():
                roles.add_row(str(n), role, f"{ref:.0f}", f"{fast:.0f}", f"{ref / fast:.2f}x")
        console.print(roles)
        if json_out is not None:
            json_out.parent.mkdir(parents=True, exist_ok=True)
            meta = {"python": platform.python_version(), "cpus": os.cpu_count(), "loadavg": load, "k": k,
                    "number": number, "repeat": repeat, "cold": cold}
            json_out.write_text(json.dumps({"meta": meta, "rows": codec_rows_as_dicts(rows),
                                            "roles": {str(n): r for n, r in per_role.items()}}, indent=2) + "\n")
            typer.echo(f"wrote {json_out}")

    @bench.command("loop-floor")
    def loop_floor(
        steps: Annotated[int, typer.Option(min=50, help="timed vector steps per topology and mode")] = 1000,
        k: Annotated[int, typer.Option(min=1, help="env copies per message (K)")] = 32,
        json_out: Annotated[Path | None, typer.Option("--json", help="also write the figures as JSON")] = None,
    ) -> None:
        """Latency floor of the step loop: env -> central -> local agents -> env with every role's
        work removed (same keys, publishers and subscriptions as `hammer up`), typed messages vs raw
        bytes, one process per local agent vs one for all. Compare with `hammer bench runtime`."""
        import os
        import platform

        from rich.table import Table

        from hammer.console import table_console
        from protocol.loopfloor import rows_as_dicts as floor_dicts
        from protocol.loopfloor import run_floor

        rows = run_floor(k=k, steps=steps)
        load = os.getloadavg()
        table = Table(title=f"hammer bench loop-floor (us per vector step, K={k}, loopback, no work in any role; "
                            f"load {load[0]:.2f})")
        for col in ("N", "local agents", "payload", "processes", "p50 us", "p99 us", "steps"):
            table.add_column(col, justify="left" if col in ("local agents", "payload") else "right")
        for n, r in rows:
            table.add_row(str(n), "one process each" if r.topology == "split" else "one process for all",
                          r.mode, str(r.processes), f"{r.p50_us:.0f}", f"{r.p99_us:.0f}", str(r.steps))
        console = table_console()
        console.print(table)
        if json_out is not None:
            json_out.parent.mkdir(parents=True, exist_ok=True)
            meta = {"python": platform.python_version(), "cpus": os.cpu_count(), "loadavg": load, "k": k,
                    "steps": steps}
            json_out.write_text(json.dumps({"meta": meta, "rows": floor_dicts(rows)}, indent=2) + "\n")
            typer.echo(f"wrote {json_out}")
