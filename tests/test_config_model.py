"""protocol/config_model.py: the part of pydantic's API the settings models use, without pydantic."""

from __future__ import annotations

import json
import pickle
import subprocess
import sys

import pytest
from hammer.protocol.config_model import ValidationError
from hammer.protocol.fault_injection import FaultRule, FaultSpec
from hammer.protocol.session import TransportConfig
from hammer.runtime.settings import RuntimeSettings


def test_lax_inputs_as_pydantic_took_them():
    r = FaultRule(drop="0.2", reorder_window="3", delay_ms=5)  # --fault strings, YAML/JSON ints
    assert (r.drop, r.reorder_window, r.delay_ms) == (0.2, 3, 5.0) and isinstance(r.delay_ms, float)
    s = RuntimeSettings(run_id="x", trace="true", hub_port=7447.0, faults={"rules": [{"drop": 0.1}]})
    assert s.trace is True and s.hub_port == 7447 and isinstance(s.faults, FaultSpec) and s.faults.enabled


@pytest.mark.parametrize("kw, loc, words", [
    ({"drop": 1.5}, ("drop",), "less than or equal to 1"),
    ({"reorder_window": 2.5}, ("reorder_window",), "fractional part"),
    ({"drop": True}, ("drop",), "not a boolean"),
    ({"match": "a//b"}, ("match",), "bad chunk"),
    ({"loss": 0.1}, ("loss",), "Extra inputs are not permitted"),
])
def test_each_error_names_its_field(kw, loc, words):
    with pytest.raises(ValidationError, match=words) as e:
        FaultRule(**kw)
    (row,) = e.value.errors(include_url=False)
    assert row["loc"] == loc and "\n" not in str(e.value)


def test_nested_and_model_level_errors():
    with pytest.raises(ValidationError) as e:
        RuntimeSettings.model_validate({"run_id": "x", "fallback": "nope", "faults": {"rules": [{"drop": 2}]}})
    assert [r["loc"] for r in e.value.errors()] == [("fallback",), ("faults", "rules", 0, "drop")]
    assert "'zeros', 'last' or 'last_k'" in str(e.value)
    with pytest.raises(ValidationError, match="mode=eval needs policy_dir") as e:
        RuntimeSettings(run_id="x", mode="eval")
    assert e.value.errors()[0]["loc"] == ()
    assert pickle.loads(pickle.dumps(e.value)).errors() == e.value.errors()
    with pytest.raises(ValidationError, match="run_id: Field required"):
        RuntimeSettings()


def test_fields_set_dump_copy_and_json():
    t = TransportConfig(listen=["tcp/127.0.0.1:1"])
    assert t.model_fields_set == {"listen"} and t.model_dump(exclude_unset=True) == {"listen": ["tcp/127.0.0.1:1"]}
    u = t.model_copy(update={"lease_ms": 1000})
    assert u.model_fields_set == {"listen", "lease_ms"} and t.lease_ms is None and u != t
    assert TransportConfig.model_validate(t.model_dump()) == t
    s = RuntimeSettings(run_id="x", faults={"seed": 2, "rules": [{"match": "agent/act/*", "drop": 0.5}]})
    assert RuntimeSettings.model_validate(json.loads(s.model_dump_json(indent=1))) == s
    assert "msg_deadline_ms" in RuntimeSettings.model_fields and RuntimeSettings.model_fields["external"].get_default(
        call_default_factory=True) == []
    assert pickle.loads(pickle.dumps(s)) == s


def test_the_config_models_import_no_pydantic():
    code = ("import sys; import hammer.protocol.config_model, hammer.protocol.fault_injection, hammer.faults.spec, "
            "hammer.faults.links, hammer.faults.steplog; print('pydantic' in sys.modules)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60)
    assert r.stdout.strip() == "False"
