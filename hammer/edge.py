"""The robot-side SDK, as `hammer.edge`: `EdgeAgent(bundle, agent=i, run_id=..., connect=...)` and
`agent.act(obs)` in a robot's own control loop (serve/edge_agent.py; docs/fleet.md). Torch-free."""

from hammer.serve.edge_agent import EdgeAgent, EdgeCounters

__all__ = ["EdgeAgent", "EdgeCounters"]
