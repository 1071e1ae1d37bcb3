"""The runtime settings of a served team: what `hammer serve`, the fault sweeps and the tests use
to serve a bundle (eval mode, its policy and fallback, link faults, process chaos, --runtime items)."""

from __future__ import annotations


def serve_settings(bundle, run_id: str, fault: list[str] | None = None, fault_seed: int = 0,
                   chaos: list[str] | None = None, runtime: list[str] | None = None, listen: list[str] | None = None):
    """RuntimeSettings of a served bundle: eval mode, its policy, its fallback, faults, chaos, --runtime items,
    the hub's --listen endpoints. Raises ValueError with a one-line reason."""
    import yaml
    from hammer.faults.chaos import parse_chaos
    from hammer.faults.spec import build_plan
    from hammer.protocol.config_model import ValidationError
    from hammer.runtime.settings import RuntimeSettings

    plan = build_plan(fault, fault_seed)
    for c in chaos or []:
        parse_chaos(c)
    fb = bundle.manifest.get("fallback", {})
    rt = {"run_id": run_id.replace("_", "-")[:64], "mode": "eval", "policy_dir": str(bundle.policy_dir),
          "fallback": fb.get("mode", "zeros"), "fallback_k": fb.get("k", 3), "chaos": chaos or []}
    if plan.links:
        rt.update(faults=plan.to_spec(), fault_links=[lf.model_dump() for lf in plan.links])
    if listen:
        rt["hub_listen"] = list(listen)
    for item in runtime or []:
        key, eq, val = item.partition("=")
        if not eq:
            raise ValueError(f"--runtime {item!r}: expected FIELD=VALUE, e.g. msg_deadline_ms=20")
        if key.strip() == "num_envs":  # a config field, not a runtime setting: what users reach for first
            raise ValueError(f"--runtime {item!r}: num_envs is not a runtime setting; fix: pass --num-envs {val.strip()}")
        rt[key.strip()] = yaml.safe_load(val)
    try:
        return RuntimeSettings.model_validate(rt), plan
    except ValidationError as e:  # one line naming each field
        raise ValueError("; ".join(f"{'.'.join(map(str, x['loc'])) or 'runtime settings'}: "
                                   f"{x['msg'].removeprefix('Value error, ')}" for x in e.errors(include_url=False))) \
            from None
