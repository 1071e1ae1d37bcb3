"""`hammer view RUNS_DIR`, and `--view [ADDR:]PORT` / `--view-token` shared by the launchers."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from hammer.commands.common import fail

ViewOpt = Annotated[str | None, typer.Option(
    "--view", metavar="[ADDR:]PORT",
    help="Also serve the run in a browser (`hammer view` on the run's folder, stopped with the run): its URL is "
         "printed. Loopback unless ADDR says otherwise; beyond loopback only with --view-token (docs/view.md).")]
ViewTokenOpt = Annotated[str | None, typer.Option(
    "--view-token", help="The token a browser or Prometheus must show to the view (default: $HAMMER_VIEW_TOKEN); "
                         "needed beyond loopback, at least 16 characters.")]


def register(app: typer.Typer) -> None:
    app.command("view")(view_command)


def view_command(
    runs_dir: Annotated[Path, typer.Argument(help="A folder of run directories (e.g. runs/), or one run directory.")] = Path("runs"),
    addr: Annotated[str, typer.Option(metavar="[ADDR:]PORT", help="Where to listen; loopback unless ADDR says "
                                      "otherwise, and beyond loopback only with a token.")] = "127.0.0.1:8050",
    token: ViewTokenOpt = None,
) -> None:
    """Watch runs and fleets in a browser, read-only: an index of runs, a live page per run (every role and
    robot ever seen, silent ones greyed with their last-seen age; alerts and events; plots), and /metrics for
    Prometheus. Needs the `view` extra (pip install 'hammer-marl[view]'). docs/view.md."""
    from hammer.deploy.live import check_view_addr, parse_view_addr, view_token
    from hammer.runtime.process import parent_watchdog

    try:
        host, port = parse_view_addr(addr)
        secret = view_token(token)
        check_view_addr(host, secret, "--addr")
    except ValueError as e:
        fail(str(e))
    if not runs_dir.is_dir():
        fail(f"{runs_dir}: no such folder; fix: give the folder that holds the run directories (e.g. runs)")
    try:
        from hammer.view.web_server import serve
    except ImportError as e:
        fail(f"hammer view needs the view extra ({e.name} is missing); fix: pip install 'hammer-marl[view]'")
    parent_watchdog()  # started by a launcher (--view): gone with it
    shown = f"[{host}]" if ":" in host else host
    typer.echo(f"hammer view: http://{shown}:{port}/ ({runs_dir}){' (token required)' if secret else ''}", err=True)
    serve(runs_dir, host, port, secret)
