"""`hammer site`: a site's identities, made once and kept (protocol/identity.py, docs/security.md).

`hammer site init DIR` makes the site's CA (its key stays in DIR, mode 0600); `hammer site issue DIR
local-<i>` issues a robot's identity, the three files the robot copies (DIR/robots/local-<i>/);
`--rotate` replaces one robot's identity, `hammer site revoke` takes one robot out; no other robot's
files change. `hammer serve --realtime --secure --site DIR` runs a fleet with them, so a restarted
fleet admits the robots it admitted before without a file copied.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from hammer.commands.common import fail

SiteArg = Annotated[Path, typer.Argument(help="The site's directory (holds its CA key: keep it on the serving machine).")]
RoleArg = Annotated[str, typer.Argument(help="The robot's role, local-<i> (e.g. local-0), or site (the site feed's "
                                               "publisher, a warehouse management system: docs/fleet.md).")]


def register(app: typer.Typer) -> None:
    site = typer.Typer(help="A site's identities, kept across fleet restarts: init, issue, rotate, revoke, list.",
                       no_args_is_help=True)
    site.command("init")(init_command)
    site.command("issue")(issue_command)
    site.command("revoke")(revoke_command)
    site.command("list")(list_command)
    app.add_typer(site, name="site")


def init_command(site: SiteArg) -> None:
    """Make the site's CA once (DIR/ca.pem, DIR/ca.key mode 0600, DIR mode 0700)."""
    from hammer.protocol.identity import SiteError, init_site

    try:
        init_site(site)
    except SiteError as e:
        fail(str(e))
    typer.echo(f"site CA made in {site} (keep {site}/ca.key on this machine); next: hammer site issue {site} local-0")


def issue_command(site: SiteArg, role: RoleArg,
                  rotate: Annotated[bool, typer.Option(help="Replace the robot's identity: the old one is revoked "
                                                            "and the robot needs the new files.")] = False,
                  host: Annotated[list[str] | None, typer.Option(
                      "--host", help="A name or address the certificate also names (repeatable).")] = None) -> None:
    """Issue a robot's identity: DIR/robots/ROLE/{ca.pem,ROLE.pem,ROLE.key}, the files the robot copies."""
    from hammer.protocol.identity import SiteError, issue_robot

    try:
        ident = issue_robot(site, role, tuple(host or ()), rotate=rotate)
    except SiteError as e:
        fail(str(e))
    typer.echo(f"{role}: {ident.ca.parent}/{{ca.pem,{role}.pem,{role}.key}} -> copy to the robot's identity folder "
               f"(mode 600); a running fleet takes it at its next start")


def revoke_command(site: SiteArg, role: RoleArg) -> None:
    """Take one robot out of the site: refused at the TLS handshake from the fleet's next start."""
    from hammer.protocol.identity import SiteError, revoke_robot

    try:
        r = revoke_robot(site, role)
    except SiteError as e:
        fail(str(e))
    typer.echo(f"{role} revoked (serial {r['serial']}); restart the fleet (`hammer serve ... --site {site}`) to refuse "
               "it now; the other robots keep their files")


def list_command(site: SiteArg) -> None:
    """The site's robots in good standing, and what was revoked."""
    from hammer.protocol.identity import SiteError, revoked, site_ca, site_robots

    try:
        site_ca(site)
    except SiteError as e:
        fail(str(e))
    for role, r in site_robots(site).items():
        typer.echo(f"{role}  serial {r['serial']}  valid until {r['not_after']}")
    for r in revoked(site):
        typer.echo(f"{r['role']}  serial {r['serial']}  {r['why']} {r['at']}")
