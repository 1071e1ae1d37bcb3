"""The runtime settings of a served team: what `hammer serve`, `hammer serve --realtime`, the fault
sweeps and the tests use to serve a bundle (eval mode, its policy and fallback, link faults, process
chaos, --runtime items), made by the one settings path (`runtime.settings.build_settings`)."""

from __future__ import annotations


def serve_settings(bundle, run_id: str, fault: list[str] | None = None, fault_seed: int = 0,
                   chaos: list[str] | None = None, runtime: list[str] | None = None, listen: list[str] | None = None,
                   fixed: dict | None = None):
    """(RuntimeSettings, FaultPlan) of a served bundle: eval mode, its policy, its fallback, faults, chaos,
    the hub's --listen endpoints, then the --runtime items, then `fixed` (the command's flags: --secure,
    --insecure). Raises ValueError with a one-line reason."""
    from hammer.faults.chaos import parse_chaos
    from hammer.faults.spec import build_plan
    from hammer.protocol.structs import dump
    from hammer.runtime.settings import build_settings

    plan = build_plan(fault, fault_seed)
    for c in chaos or []:
        parse_chaos(c)
    fb = bundle.manifest.get("fallback", {})
    rt = {"run_id": run_id.replace("_", "-")[:64], "mode": "eval", "policy_dir": str(bundle.policy_dir),
          "fallback": fb.get("mode", "zeros"), "fallback_k": fb.get("k", 3), "chaos": chaos or []}
    if plan.links:
        rt.update(faults=plan.to_spec(), fault_links=[dump(lf) for lf in plan.links])
    if listen:
        rt["hub_listen"] = list(listen)
    return build_settings(rt, runtime, fixed=fixed), plan
