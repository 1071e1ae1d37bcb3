"""protocol/structs.py: the settings (runtime, transport, faults) as msgspec Structs, validated
however they are made, with errors in one line naming the field, and no pydantic."""

from __future__ import annotations

import json
import pickle
import subprocess
import sys

import pytest
from hammer.protocol.fault_injection import FaultRule, FaultSpec
from hammer.protocol.session import TransportConfig
from hammer.protocol.structs import SettingsError, dump, parse, replace
from hammer.runtime.settings import RuntimeSettings, build_settings


def test_lax_inputs_from_strings_and_integral_floats():
    r = parse(FaultRule, {"drop": "0.2", "reorder_window": "3", "delay_ms": 5})  # --fault strings, YAML/JSON ints
    assert (r.drop, r.reorder_window, r.delay_ms) == (0.2, 3, 5.0) and isinstance(r.delay_ms, float)
    s = RuntimeSettings(run_id="x", trace="true", hub_port=7447.0, faults={"rules": [{"drop": 0.1}]})
    assert s.trace is True and s.hub_port == 7447 and isinstance(s.faults, FaultSpec) and s.faults.enabled


@pytest.mark.parametrize("data, field, words", [
    ({"drop": 1.5}, "drop", "should be a number <= 1.0"),
    ({"delay_ms": -1}, "delay_ms", "should be a number >= 0.0"),
    ({"reorder_max_hold_ms": 0}, "reorder_max_hold_ms", "should be a number > 0.0"),
    ({"reorder_window": 0}, "reorder_window", "should be an integer >= 1"),
    ({"reorder_window": 2.5}, "reorder_window", "should be an integer, not a number"),
    ({"drop": True}, "drop", "should be a number, not a boolean"),
    ({"drop": "lots"}, "drop", "should be a number, not a string"),
    ({"match": "a//b"}, "", "match: bad chunk"),
    ({"loss": 0.1}, "loss", "unknown field"),
])
def test_each_error_is_one_line_naming_its_field(data, field, words):
    for make in (lambda: parse(FaultRule, data), lambda: FaultRule(**data) if "loss" not in data else parse(FaultRule, data)):
        with pytest.raises(SettingsError) as e:
            make()
        assert e.value.field == field and words in str(e.value) and "\n" not in str(e.value), str(e.value)
        assert str(e.value).startswith(f"FaultRule: {field + ': ' if field else ''}")


def test_unknown_keys_nested_errors_and_cross_field_rules():
    with pytest.raises(SettingsError, match=r"faults\.rules\[0\]\.drop: should be a number <= 1.0"):
        parse(RuntimeSettings, {"run_id": "x", "faults": {"rules": [{"drop": 2}]}})
    with pytest.raises(SettingsError, match=r"faults\.rules\[1\]\.loss: unknown field") as e:
        parse(RuntimeSettings, {"run_id": "x", "faults": {"rules": [{}, {"loss": 1}]}})
    assert e.value.kind == "unknown"
    with pytest.raises(SettingsError, match="fallback: 'nope' is not a choice; fix: one of zeros, last, last_k"):
        parse(RuntimeSettings, {"run_id": "x", "fallback": "nope"})
    with pytest.raises(SettingsError, match="mode=eval needs policy_dir") as e:
        RuntimeSettings(run_id="x", mode="eval")
    assert e.value.field == "" and str(pickle.loads(pickle.dumps(e.value))) == str(e.value)
    with pytest.raises(SettingsError, match="run_id: required, not given"):
        parse(RuntimeSettings, {})
    with pytest.raises(SettingsError, match="secure=true and insecure=true"):  # a copy is checked like a new one
        replace(RuntimeSettings(run_id="x", secure=True), insecure=True)


def test_the_runtime_flag_says_the_field_the_fix_and_what_it_got():
    for items, says in ((["hub_port=abc"], "--runtime hub_port: should be an integer, not a string (got 'abc')"),
                        (["hub_port=70000"], "--runtime hub_port: should be an integer <= 65535 (got 70000)"),
                        (["msg_deadline=20"], "--runtime msg_deadline: unknown field; fix: did you mean 'msg_deadline_ms'?"),
                        (["weights_chunk_bytes=10"], "weights_chunk_bytes=10: a chunk of under 64 B")):
        with pytest.raises(ValueError) as e:
            build_settings({"run_id": "x"}, items)
        assert says in str(e.value) and "\n" not in str(e.value), str(e.value)
    assert build_settings({"run_id": "x"}, ["msg_deadline_ms=20", "trace=true"]).msg_deadline_ms == 20.0


def test_not_given_is_none_and_a_zenoh_file_keeps_what_is_not_given(tmp_path):
    f = tmp_path / "z.json5"
    f.write_text('{mode: "client", connect: {endpoints: ["tcp/127.0.0.1:7447"], retry: {period_max_ms: 3000}}}')
    t = TransportConfig(zenoh_config_file=f)  # a Path is taken, kept as its string
    assert t.mode is None and t.reconnect_max_ms is None and t.zenoh_config_file == str(f)
    c = t.to_zenoh()
    assert json.loads(c.get_json("mode")) == "client" and json.loads(c.get_json("connect/retry"))["period_max_ms"] == 3000
    c = replace(t, mode="peer", reconnect_max_ms=1000).to_zenoh()
    assert json.loads(c.get_json("mode")) == "peer" and json.loads(c.get_json("connect/retry"))["period_max_ms"] == 1000
    plain = TransportConfig(listen=["tcp/127.0.0.1:1"]).to_zenoh()
    assert json.loads(plain.get_json("mode")) == "peer" and json.loads(plain.get_json("connect/retry"))["period_max_ms"] == 500


def test_dump_load_and_the_runtime_json(tmp_path):
    s = RuntimeSettings(run_id="x", faults={"seed": 2, "rules": [{"match": "agent/act/*", "drop": 0.5}]})
    assert parse(RuntimeSettings, json.loads(json.dumps(dump(s)))) == s and pickle.loads(pickle.dumps(s)) == s
    s.save(tmp_path)
    written = json.loads((tmp_path / "runtime.json").read_text())
    assert RuntimeSettings.load(tmp_path) == s and written["faults"]["rules"][0]["drop"] == 0.5
    # a default runtime.json names no bound and none of the fields written only when set
    assert not {"step_window", "reconnect_max_s", "secure", "external", "hub_listen"} & set(written), written
    assert list(written)[:3] == ["run_id", "hub_port", "zenoh_config_file"]  # the fields' order


def test_the_settings_import_no_pydantic():
    code = ("import sys; import hammer.protocol.structs, hammer.protocol.fault_injection, hammer.faults.spec, "
            "hammer.runtime.settings, hammer.faults.links, hammer.faults.steplog; print('pydantic' in sys.modules)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60)
    assert r.stdout.strip() == "False"
