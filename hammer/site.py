"""The site feed SDK, as `hammer.site`: `SiteFeed(bundle, run_id=..., connect=...)` and
`feed.publish(state)` from a warehouse management system: what a fleet's central agent sees that no
robot observes (serve/site_feed.py; docs/fleet.md "The site feed"). `simulated_warehouse(run_dir)`:
in a simulated fleet, the warehouse's current columns as its world writes them. Torch-free."""

from hammer.serve.site_feed import SiteFeed, simulated_warehouse

__all__ = ["SiteFeed", "simulated_warehouse"]
