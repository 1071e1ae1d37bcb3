"""What every command shares, defined once: the one-line error and the options several commands take
(as zenoh-python's examples share `add_config_arguments`)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, NoReturn

import typer
import typer.core

RunDirOpt = Annotated[Path, typer.Option(help="Run directory made by `hammer up` (config.json, runtime.json, env_spec.json).")]
ConnectOpt = Annotated[str | None, typer.Option(help="Zenoh endpoint of the hub, e.g. tcp/127.0.0.1:7447 (default: from runtime.json).")]
ZenohCfgOpt = Annotated[Path | None, typer.Option(help="Zenoh JSON5 config (router/client/TLS deployments).")]
SecureOpt = Annotated[bool, typer.Option(
    help="Mutual TLS with per-run identities (RUN/identity/) and per-role access rules (docs/security.md); "
         "the same as --runtime secure=true.")]
InsecureOpt = Annotated[bool, typer.Option(
    help="Accept the plain profile beyond loopback (a Zenoh config reaching other machines): only on a "
         "network you trust; the same as --runtime insecure=true.")]
ListenOpt = Annotated[list[str] | None, typer.Option(
    "--listen", help="Also listen on this endpoint for agents on other machines, e.g. tcp/192.0.2.1:7447 (this "
                     "machine's address they reach, a fixed port; repeatable); the run's own roles stay on loopback. "
                     "Beyond loopback it needs --secure or --insecure.")]


class ConfigFieldsHelp(typer.core.TyperCommand):
    """A command that takes RunConfig fields (--set, --config): its help ends with every field, default and
    description, read from the model only when the help is shown (the model loads pydantic)."""

    def format_help(self, ctx, formatter) -> None:
        if self.epilog is None:
            from hammer.learning.config import fields_help

            self.epilog = ("Config fields (--set FIELD=VALUE or a --config YAML file; a preset changes some of "
                           "these defaults):\n\n" + fields_help())
        super().format_help(ctx, formatter)


def fail(msg: str, code: int = 2) -> NoReturn:
    """End the command with `error: msg` on stderr, in red, and exit status `code` (2: a usage error)."""
    typer.secho(f"error: {msg}", fg=typer.colors.RED, err=True)
    raise typer.Exit(code)
