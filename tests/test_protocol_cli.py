"""`hammer protocol schema`, `hammer bench transport` and `hammer bench codec` (tiny counts: they must
run, not be fast)."""

from __future__ import annotations

import json

from hammer.protocol.schemas import MESSAGE_TYPES
from typer.testing import CliRunner

from hammer.cli import app


def test_schema_command_writes_every_message(tmp_path):
    out = tmp_path / "schema.json"
    result = CliRunner().invoke(app, ["protocol", "schema", "--out", str(out)])
    assert result.exit_code == 0, result.output
    data = json.loads(out.read_text())
    assert set(data["messages"]) == set(MESSAGE_TYPES)
    central = data["messages"]["central_msg"]  # a msgpack array: the type tag, then the fields in order
    msg = central["prefixItems"][central["fields"].index("msg")]
    assert (msg["minItems"], msg["maxItems"], len(msg["prefixItems"])) == (3, 3, 3)  # [dtype code, shape, data]


def test_bench_transport_runs_and_writes_json(tmp_path):
    out = tmp_path / "bench.json"
    result = CliRunner().invoke(app, ["bench", "transport", "--rounds", "20", "--flood", "200", "--json", str(out)])
    assert result.exit_code == 0, result.output
    data = json.loads(out.read_text())
    names = [r["payload"] for r in data["rows"]]
    assert names == ["local_obs K=1 D=18", "global_state K=1 N=3 D=18", "global_state K=1 N=5 D=30",
                     "global_state K=64 N=3 D=18"]
    for r in data["rows"]:
        assert r["typed_msgs_per_s"] > 0 and r["raw_msgs_per_s"] > 0
        assert 0 < r["typed_rtt_p50_us"] <= r["typed_rtt_p99_us"]
        assert r["rate_ratio"] == r["typed_msgs_per_s"] / r["raw_msgs_per_s"]
    # The K=64 batch carries 64x the data of one copy in one message.
    assert data["rows"][3]["bytes"] > 30 * data["rows"][1]["bytes"] // 2
    assert "typed" in result.output and "raw" in result.output


def test_bench_codec_runs_and_writes_json(tmp_path):
    out = tmp_path / "codec.json"
    result = CliRunner().invoke(app, ["bench", "codec", "--k", "4", "--number", "10", "--repeat", "1",
                                      "--json", str(out)])
    assert result.exit_code == 0, result.output
    data = json.loads(out.read_text())
    names = [r["payload"] for r in data["rows"]]
    assert len(names) == 8 and names[0] == "global_state K=4 N=3 D=18 M=4" and names[4].endswith("N=5 D=30 M=8")
    for r in data["rows"]:
        for col in ("build", "encode", "decode", "unpackb"):
            assert r[f"{col}_us"] > 0
        assert r["total_us"] == r["build_us"] + r["encode_us"] + r["decode_us"]
    assert set(data["roles"]) == {"3", "5"}
    for roles in data["roles"].values():
        assert set(roles) == {"env host", "central agent", "local agent"}
    assert "unpackb" in result.output and "local agent" in result.output


def test_bench_codec_cold_mode_runs(tmp_path):
    out = tmp_path / "cold.json"
    result = CliRunner().invoke(app, ["bench", "codec", "--k", "2", "--number", "2", "--cold", "--json", str(out)])
    assert result.exit_code == 0, result.output
    data = json.loads(out.read_text())
    assert data["meta"]["cold"] is True and len(data["rows"]) == 8
    assert all(r["decode_us"] > 0 and r["unpackb_us"] > 0 for r in data["rows"])
    assert "cache-cold" in result.output


def test_bench_wire_counts_each_links_bytes_against_the_minimum(tmp_path):
    """The compact wire: per link, the encoded messages of one step add up, and the minimum is the
    numbers alone (cn3 own-observation: 57 B an agent link, 171 B the central, at K=1)."""
    out = tmp_path / "wire.json"
    r = CliRunner().invoke(app, ["bench", "wire", "--num-envs", "1,32", "--out", str(out)])
    assert r.exit_code == 0, r.output
    rows = {row["K"]: row for row in json.loads(out.read_text())["rows"]}
    assert (rows[1]["agent_link_min"], rows[1]["central_link_min"]) == (57, 171)
    assert rows[32]["agent_link_min"] == 32 * 57
    for row in rows.values():
        assert row["agent_link"] == row["local_obs_training"] + row["central_msg"] + row["action"]
        assert row["local_obs_training"] == row["local_obs"] + 1  # the echo flag (true) of a training observation
        assert row["agent_link_eval"] == row["local_obs"] + row["central_msg"] + row["action_without_echoed_msg"]
        assert row["central_link"] == row["global_state"] + 3 * row["central_msg"]
        assert row["action"] > row["action_without_echoed_msg"]  # the echo is counted, and visible
        assert row["agent_link"] > row["agent_link_min"]
    assert rows[1]["agent_link_ratio"] > rows[32]["agent_link_ratio"]  # headers weigh most on one copy
    # Constrained links: at one env copy a serving agent's link and the central link carry at most twice the
    # numbers themselves (training adds the echoed message the rollout records).
    assert rows[1]["agent_link_eval"] <= 2 * rows[1]["agent_link_min"], rows[1]
    assert rows[1]["central_link"] <= 2 * rows[1]["central_link_min"], rows[1]
    assert rows[32]["agent_link"] <= 1.5 * rows[32]["agent_link_min"], rows[32]


def test_bench_peers_says_why_it_skips_without_jaxmarls_baselines(tmp_path):
    """JaxMARL's IPPO baseline lives in its repository, not its pip package: without it the bench
    says so and how to get it, and builds nothing."""
    venv = tmp_path / "jax-venv"
    r = CliRunner().invoke(app, ["bench", "peers", "--jaxmarl-repo", str(tmp_path), "--jax-venv", str(venv)])
    assert r.exit_code == 0 and "skipped" in r.output and "FLAIROx/JaxMARL" in r.output, r.output
    assert not venv.exists()


def test_bench_peers_names_an_unknown_schedule_and_the_choices(tmp_path):
    r = CliRunner().invoke(app, ["bench", "peers", "--jaxmarl-repo", str(tmp_path), "--jax-venv", str(tmp_path / "v"),
                                 "--hammer-schedules", "cn3,k9000"])
    assert r.exit_code != 0
    text = r.output + str(r.exception or "")
    assert "k9000" in text and "jaxmarl-ppo-k256" in text, text
