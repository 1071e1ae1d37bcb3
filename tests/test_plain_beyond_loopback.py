"""Secure by default beyond loopback: a plain run trusts whoever reaches its port, so every
command that listens on or connects to an address other than loopback refuses the plain profile in
one line naming the endpoint and the fixes, unless told `--insecure`; loopback keeps the plain default."""

from __future__ import annotations

import json

import pytest
from hammer.protocol.session import TransportConfig
from hammer.runtime.settings import RuntimeSettings, refuse_plain_beyond_loopback
from typer.testing import CliRunner

from hammer.cli import app


@pytest.mark.parametrize(("transport", "out"), [
    (TransportConfig(listen=["tcp/127.0.0.1:7447"], connect=["tcp/localhost:7448", "tls/[::1]:7449"]), []),
    # 192.0.2.1: TEST-NET-1 (RFC 5737), reserved for examples and never routed; nothing here connects
    (TransportConfig(connect=["tcp/192.0.2.1:7447"]), ["tcp/192.0.2.1:7447"]),
    (TransportConfig(listen=["tcp/0.0.0.0:0"]), ["tcp/0.0.0.0:0"]),
    (TransportConfig(connect=["tcp/robot-7.local:7447"]), ["tcp/robot-7.local:7447"]),  # a name may resolve anywhere
])
def test_what_reaches_past_this_machine(transport, out):
    assert transport.beyond_loopback() == out


def test_a_zenoh_config_is_read_for_its_endpoints_and_scouting(tmp_path):
    def cfg(d: dict) -> TransportConfig:
        path = tmp_path / f"z{len(list(tmp_path.iterdir()))}.json5"
        path.write_text(json.dumps(d))
        return TransportConfig(zenoh_config_file=path)

    off = {"scouting": {"multicast": {"enabled": False}}}
    assert cfg({"mode": "client", "connect": {"endpoints": ["tcp/127.0.0.1:7447"]}, **off}).beyond_loopback() == []
    assert cfg({"mode": "client", "connect": {"endpoints": ["tcp/127.0.0.1:7447"]}}).beyond_loopback() == \
        ["multicast scouting"]  # Zenoh's default scouts the whole LAN
    assert cfg({"mode": "router", "listen": {"endpoints": {"router": ["tcp/0.0.0.0:7447"]}}, **off}).beyond_loopback() \
        == ["tcp/0.0.0.0:7447"]


def test_the_refusal_is_one_line_with_both_fixes_and_insecure_or_secure_pass():
    t = TransportConfig(connect=["tcp/192.0.2.1:7447"])
    with pytest.raises(ValueError) as e:
        refuse_plain_beyond_loopback(t, secure=False, insecure=False)
    msg = str(e.value)
    assert "\n" not in msg and "tcp/192.0.2.1:7447" in msg and "--secure" in msg and "--insecure" in msg
    refuse_plain_beyond_loopback(t, secure=False, insecure=True)
    refuse_plain_beyond_loopback(t, secure=True, insecure=False)
    RuntimeSettings(run_id="r", insecure=True).refuse_plain_beyond_loopback(t)  # the run's recorded consent
    with pytest.raises(ValueError, match="contradict"):
        RuntimeSettings(run_id="r", secure=True, insecure=True)


def test_hammer_hub_on_a_lan_address_refuses_plain_and_names_its_own_fix():
    res = CliRunner().invoke(app, ["hub", "--listen", "tcp/0.0.0.0:7447"])
    assert res.exit_code == 2 and res.output.count("\n") == 1, res.output
    assert "refusing to run plain on tcp/0.0.0.0:7447" in res.output and "--run-dir RUN" in res.output


def test_hammer_up_with_a_zenoh_config_beyond_loopback_refuses_before_starting_anything(tmp_path):
    z = tmp_path / "lan.json5"
    z.write_text(json.dumps({"mode": "peer", "listen": {"endpoints": ["tcp/0.0.0.0:7447"]},
                             "scouting": {"multicast": {"enabled": False}}}))
    res = CliRunner().invoke(app, ["up", "--episodes", "1", "--variant", "il", "--run-dir", str(tmp_path / "run"),
                                   "--no-dashboard", "--runtime", f"zenoh_config_file={z}"])
    assert res.exit_code != 0 and "refusing to run plain on tcp/0.0.0.0:7447" in res.output, res.output
    assert "--insecure" in res.output and not (tmp_path / "run" / "logs").exists()  # no role was started
