"""The launchers write their roles' command lines (deploy/, which may not import the commands in
hammer/): every line they make must parse with the command's own parser, so renaming a role
command's option fails here rather than in a run."""

from __future__ import annotations

import shlex
from pathlib import Path

import pytest
import typer
from hammer.deploy.fleet_launch import FleetPlan, apply_runtime, robot_command
from hammer.deploy.fleet_launch import role_specs as fleet_specs
from hammer.deploy.launcher import role_specs as up_specs
from hammer.deploy.supervisor import role_args
from hammer.learning.config import merge_config
from hammer.runtime.settings import RuntimeSettings

from hammer.cli import app
from hammer.commands.edge import is_edge, parser


def _parse(args: list[str]) -> None:
    """Parse `hammer ARGS` as the console script would, running nothing; raise on a bad option."""
    if is_edge(args):
        try:
            parser().parse_args(args[1:])
        except SystemExit:
            raise AssertionError(f"`hammer {shlex.join(args)}`: refused by the edge parser") from None
        return
    group = typer.main.get_command(app)
    command = group.commands[args[0]]
    try:
        command.make_context(args[0], list(args[1:]))
    except Exception as e:  # noqa: BLE001 - typer's own click: its UsageError (an unknown option, a bad value)
        raise AssertionError(f"`hammer {shlex.join(args)}`: {e}") from None


def test_role_args_writes_options_in_order():
    assert role_args("local", run_dir=Path("r"), agent=2, fleet=True, seed=None, insecure=False,
                     runtime=["a=1", "b=2"]) == ["local", "--run-dir", "r", "--agent", "2", "--fleet",
                                                 "--runtime", "a=1", "--runtime", "b=2"]


@pytest.mark.parametrize("per_process", [1, 2])
def test_every_role_line_of_hammer_up_parses(tmp_path, per_process):
    cfg = merge_config("cn3", None, [], {"variant": "hammer", "out": str(tmp_path)})
    settings = RuntimeSettings(run_id="r", agents_per_process=per_process, external=["local-2"])
    specs = up_specs(cfg, tmp_path / "run", settings)
    assert {s.args[0] for s in specs} == {"learner", "central", "local", "env-host"}
    for s in specs:
        _parse(s.args)


@pytest.mark.parametrize("secure", [False, True])
def test_every_role_line_of_a_fleet_parses(tmp_path, secure):
    plan = apply_runtime(FleetPlan(bundle=tmp_path / "b", hub_port=7447, external=[1], seed=3, secure=secure,
                                   timeline=tmp_path / "t.jsonl", listen=["tcp/0.0.0.0:7500"]),
                         ["zenoh_lease_s=3", "hold_s=1"])
    specs = fleet_specs(plan, "run", "tcp/127.0.0.1:7447", 3, True, tmp_path)
    assert {s.args[0] for s in specs} == {"fleet-world", "fleet-policy", "fleet-central", "local"}
    for s in specs:
        _parse(s.args)
    _parse(shlex.split(robot_command(plan, 1, tmp_path))[1:])


@pytest.mark.parametrize("secure", [False, True])
def test_every_command_hammer_serve_shows_for_an_external_role_parses(tmp_path, secure):
    from types import SimpleNamespace

    from hammer.deploy.plan import external_help

    cfg = merge_config("cn3", None, [], {"variant": "hammer", "out": str(tmp_path)})
    trained = SimpleNamespace(config_data={"num_envs": cfg.num_envs + 1})  # served with other K: --num-envs shown
    settings = RuntimeSettings(run_id="r", hub_port=7447, secure=secure, hub_listen=["tcp/0.0.0.0:7500"])
    shown = external_help(tmp_path / "b", trained, cfg, settings, tmp_path / "run", [0, 2], ["central"], 5)
    assert set(shown) == {"local-0", "local-2", "central"} and "--num-envs" in shown["local-0"]
    for line in shown.values():
        _parse(shlex.split(line.split(" (")[0])[1:])
