"""The docs and `--help` say what the code does: every `hammer ...` command line in README.md and
docs/*.md uses only options that command's `--help` lists, and the figures the help and docs quote
(defaults, the schema version) are the code's."""

from __future__ import annotations

import re
import subprocess
import sys
from functools import cache

import pytest
import typer
from typer.testing import CliRunner

from hammer.cli import app
from tests.runtime_helpers import ENV, ROOT

DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]


def _command_lines(text: str) -> list[str]:
    """Every `hammer ...` command line: in code blocks (continued lines joined) and in inline code."""
    text = re.sub(r"\\\n\s*", " ", text)
    return [m.group(1) for m in re.finditer(r"(?:^|[`$(]\s*|\n\s*)(hammer\s[^`\n|;&)#]*)", text)]


@cache
def _root():
    return typer.main.get_command(app)


def _resolve(tokens: list[str]) -> tuple[str, ...]:
    """The command path a command line names (`hammer bench soak ...` -> ("bench", "soak"))."""
    cmd, path = _root(), []
    for t in tokens:
        sub = getattr(cmd, "commands", {}).get(t)
        if sub is None:
            break
        cmd, path = sub, [*path, t]
    return tuple(path)


@cache
def _help(path: tuple[str, ...]) -> str:
    r = CliRunner().invoke(app, [*path, "--help"], terminal_width=240, env={"COLUMNS": "240"})
    assert r.exit_code == 0, r.output
    return r.output


def _doc_options() -> list[tuple[str, tuple[str, ...], str, str]]:
    """(doc, command path, option, line) for every option a doc passes to a command."""
    out = []
    for doc in DOCS:
        for line in _command_lines(doc.read_text()):
            tokens = line.split()[1:]
            path = _resolve(tokens)
            if not path:
                continue
            for t in tokens:
                name = t.split("=")[0].rstrip(".,:'\"")
                if re.fullmatch(r"--[a-z0-9][a-z0-9-]*", name):
                    out.append((doc.name, path, name, line))
    return out


def test_every_option_the_docs_pass_to_a_command_is_in_that_commands_help():
    found = _doc_options()
    assert len(found) > 300 and any(p == ("local",) and o == "--fleet" for _, p, o, _ in found)  # the scan works
    missing = [f"{doc}: hammer {' '.join(path)} {opt} (in: {line.strip()[:90]})" for doc, path, opt, line in found
               if not re.search(rf"(?<![\w-]){re.escape(opt)}(?![\w-])", _help(path))]
    assert not missing, "\n".join(missing)


def test_hammer_local_help_lists_every_option_of_the_edge_agent():
    """`hammer local --bundle` is parsed by hammer/commands/edge.py alone; the full CLI's help lists its
    options from that parser (the console script, as a user runs it)."""
    from hammer.commands.edge import parser

    r = subprocess.run([sys.executable, "-m", "hammer", "local", "--help"], capture_output=True, text=True,
                       env={**ENV, "COLUMNS": "200"}, check=True, timeout=60)
    options = [o for a in parser()._actions for o in a.option_strings if a.help != "==SUPPRESS=="]
    assert "--fleet" in options and "--max-msg-age-s" in options
    assert [o for o in options if o not in r.stdout] == []
    assert "--run-dir" in r.stdout and "--agents" in r.stdout  # the role of a `hammer up` run


@pytest.mark.parametrize("argv", [["-m", "hammer"], ["-m", "hammer.cli"]])
def test_both_entry_points_send_local_bundle_to_the_one_edge_parser(argv, tmp_path):
    r = subprocess.run([sys.executable, *argv, "local", "--bundle", str(tmp_path / "nothing"), "--agent", "0",
                        "--fleet", "--max-msg-age-s", "0.2"], capture_output=True, text=True, env=ENV, timeout=60,
                       check=False)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "nothing" in r.stderr, r.stderr


def _help_text(*args: str) -> str:
    r = subprocess.run([sys.executable, "-m", "hammer", *args, "--help"], capture_output=True, text=True,
                       env={**ENV, "COLUMNS": "200"}, check=True, timeout=60)
    return " ".join(r.stdout.split())  # wrapped lines joined


def test_a_misspelled_config_field_points_at_help_that_lists_every_field(tmp_path):
    from hammer.learning.config import RunConfig

    r = subprocess.run([sys.executable, "-m", "hammer", "train", "--preset", "cn3", "--set", "qqq_zzz=1",
                        "--run-dir", str(tmp_path / "r")], capture_output=True, text=True, env=ENV, timeout=60,
                       check=False)
    assert r.returncode == 2 and "see `hammer train --help` for the fields" in r.stderr, r.stderr
    for command in ("train", "up"):
        text = _help_text(command)
        missing = [n for n, f in RunConfig.model_fields.items()
                   if f"{n} = {f.get_default(call_default_factory=True)!r}" not in text]
        assert not missing, (command, missing)


def test_push_help_quotes_the_gates_defaults():
    from hammer.serve.canary import Gate

    text = _help_text("push")
    gate = Gate()
    assert f"default {gate.window_episodes})" in text and "default 48" not in text
    for name in ("metric_drop", "default_rate", "fallback_rate", "latency_ms", "timeout_s"):
        assert f"{name} ({getattr(gate, name):g})" in text, name


def test_readme_examples_name_paths_a_clone_has_and_change_what_they_say():
    from hammer.learning.config import merge_config
    from hammer.learning.presets import PRESETS

    lines = _command_lines((ROOT / "README.md").read_text())
    for command in ("dose", "messages"):
        line = next(ln for ln in lines if _resolve(ln.split()[1:]) == (command,))
        paths = [t for t in line.split()[2:] if not t.startswith("-") and "/" in t and not t.startswith("msgs")]
        assert paths and all((ROOT / p).is_dir() for p in paths), line
    branch = next(ln for ln in lines if "--branch" in ln and "--set" in ln)
    key, _, value = branch.split("--set", 1)[1].split()[0].partition("=")
    same = [p for p in PRESETS if str(getattr(merge_config(p), key)) == value]
    assert not same, f"{branch}: {key}={value} is already the default of {same}"


def test_deploy_md_quotes_the_schema_version_the_code_speaks():
    from hammer.protocol.schemas import SCHEMA_VERSION

    text = " ".join((ROOT / "docs" / "deploy.md").read_text().split())
    quoted = re.search(r"The messages are msgspec Structs \(schema (\d+)", text)
    assert quoted and int(quoted.group(1)) == SCHEMA_VERSION


def test_every_bench_writes_into_runs_bench_unless_told_to_publish():
    bench = _root().commands["bench"]
    params = [(name, p) for name, cmd in [("bench", bench), *bench.commands.items()] for p in cmd.params]
    dirs = {name: p.default for name, p in params if p.name == "json_dir"}
    assert "soak" in dirs and "scale" in dirs, dirs
    assert {n: d for n, d in dirs.items() if d != "runs/bench"} == {}
    assert [(n, p.name, p.default) for n, p in params if str(p.default or "").startswith("docs")] == []


def test_every_default_a_help_text_quotes_is_the_codes():
    """`default N` in an option's help is the option's default, or, where the option defaults to None
    and the code decides, what the code decides (the table below); a figure of the OS is not ours."""
    from hammer.serve.canary import Gate
    from hammer.serve.edge_entry import DEFAULT_CONNECT_RETRY_S

    from hammer.commands.edge import parser

    decided = {("push", "window_episodes"): Gate().window_episodes,
               ("local --bundle", "connect_retry_s"): DEFAULT_CONNECT_RETRY_S}

    def commands(cmd, path):
        for name, sub in getattr(cmd, "commands", {}).items():
            yield from commands(sub, (*path, name))
        if not hasattr(cmd, "commands"):
            yield " ".join(path), [(p.name, p.help or "", p.default) for p in cmd.params]

    options = [*commands(_root(), ()), ("local --bundle", [(a.dest, a.help or "", a.default) for a in parser()._actions])]
    quoted, wrong = 0, []
    for command, params in options:
        for name, text, default in params:
            for m in re.finditer(r"(\w+ )?[Dd]efault:? (-?\d[\d.,]*)", text):
                if m.group(1) == "Linux ":
                    continue
                quoted += 1
                value = float(m.group(2).rstrip(".,").replace(",", ""))
                code = decided.get((command, name), default)
                if not isinstance(code, int | float) or float(code) != value:
                    wrong.append(f"hammer {command} --{name.replace('_', '-')}: help says default {m.group(2)}, "
                                 f"the code {code!r}")
    assert quoted >= 3 and not wrong, wrong
