"""`hammer hub`: a Zenoh router in a Python process, the meeting point for multi-machine runs.

No `zenohd` binary is needed: the Python package runs in router mode. Roles on other machines
connect to it in client mode (a Zenoh JSON5 config passed with --zenoh-config), and the router
forwards their traffic; see docs/runtime.md for a two-machine walkthrough.
"""

from __future__ import annotations

import signal
import threading
from typing import Annotated

import typer


def hub_command(
    listen: Annotated[list[str], typer.Option(help="Endpoint(s) to listen on, e.g. tcp/127.0.0.1:7447 "
                                                    "(use this machine's LAN address for other machines).")],
) -> None:
    """Run a Zenoh router until Ctrl-C / SIGTERM (multicast scouting off)."""
    from protocol.session import HammerSession, TransportConfig

    try:
        transport = TransportConfig(mode="router", listen=listen)
    except ValueError as e:
        typer.secho(f"error: --listen: {' '.join(str(e).split())}", fg=typer.colors.RED, err=True)
        raise typer.Exit(2) from None
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with HammerSession("hub", transport, sender="hub"):
        typer.echo(f"hammer hub: Zenoh router listening on {', '.join(listen)}", err=True)
        try:
            while not stop.wait(0.5):
                pass
        except KeyboardInterrupt:
            pass
