"""`hammer hub`: a Zenoh router in a Python process, the meeting point for multi-machine runs.

No `zenohd` binary is needed: the Python package runs in router mode. Roles on other machines
connect to it in client mode (a Zenoh JSON5 config passed with --zenoh-config), and the router
forwards their traffic; see docs/runtime.md for a two-machine walkthrough.

`--run-dir RUN` of a secure run (runtime.json with secure=true) makes the router one of the run's
identities (RUN/identity/hub.*): it accepts mutual-TLS links only and checks the run's access
rules on every hop it relays (docs/security.md).
"""

from __future__ import annotations

import signal
import threading
from pathlib import Path
from typing import Annotated

import typer

from hammer.commands import common
from hammer.runtime.process import take_signals


def hub_command(
    listen: Annotated[list[str], typer.Option(help="Endpoint(s) to listen on, e.g. tcp/127.0.0.1:7447 "
                                                    "(use this machine's LAN address for other machines).")],
    run_dir: Annotated[Path | None, typer.Option(
        help="A secure run's directory (runtime.json, config.json, identity/): relay that run over mutual TLS "
             "and enforce its access rules.")] = None,
    insecure: Annotated[bool, typer.Option(
        help="Relay plain traffic beyond loopback (no --run-dir): only on a network you trust.")] = False,
) -> None:
    """Run a Zenoh router until Ctrl-C / SIGTERM (multicast scouting off)."""
    from hammer.protocol.session import HammerSession, TransportConfig

    try:
        transport = TransportConfig(mode="router", listen=listen)
    except ValueError as e:
        common.fail(f"--listen: {' '.join(str(e).split())}")
    run_id = "hub"
    if run_dir is not None:
        transport, run_id = _secure_hub(transport, run_dir)
    else:
        from hammer.runtime.settings import refuse_plain_beyond_loopback

        try:
            refuse_plain_beyond_loopback(transport, secure=False, insecure=insecure,
                                         fix="relay a secure run with --run-dir RUN (docs/security.md), or "
                                             "--insecure to accept plain traffic on a network you trust")
        except ValueError as e:
            common.fail(str(e))
    stop = threading.Event()
    take_signals((signal.SIGTERM,), lambda _: stop.set())
    with HammerSession(run_id, transport, sender="hub"):
        shown = ", ".join(transport.listen)
        typer.echo(f"hammer hub: Zenoh router listening on {shown}"
                   + (f" (secure, run {run_id})" if transport.security else ""), err=True)
        try:
            while not stop.wait(0.5):
                pass
        except KeyboardInterrupt:
            pass


def _secure_hub(transport, run_dir: Path):
    """The router as identity `hub` of the secure run in `run_dir`: (transport, run id)."""
    import json

    from hammer.protocol.access import HUB
    from hammer.runtime.settings import RuntimeSettings

    def fail(msg: str):
        common.fail(f"--run-dir {run_dir}: {msg}")

    try:
        settings = RuntimeSettings.load(run_dir)
        n_agents = int(json.loads((run_dir / "config.json").read_text())["n_agents"])
    except (FileNotFoundError, KeyError, ValueError) as e:
        fail(str(e))
    if not settings.secure:
        fail("runtime.json has no secure=true: a plain run needs no --run-dir")
    if not settings.secure_hub:
        fail("runtime.json has no secure_hub=true: this secure run was made for peers, so it has no router identity "
             "and its roles accept nothing relayed; fix: make the run with `hammer up --secure --runtime secure_hub=true`")
    secured = settings.secured(transport, HUB, run_dir, n_agents)
    missing = secured.security.identity.missing()
    if missing:
        fail(f"identity files missing: {', '.join(map(str, missing))}")
    return secured, settings.run_id
