"""The site feed SDK, as `hammer.site`: `SiteFeed(bundle, run_id=..., connect=...)` and
`feed.publish(state)` from a warehouse management system: what a fleet's central agent sees that no
robot observes (serve/site_feed.py; docs/fleet.md "The site feed"). Torch-free."""

from hammer.serve.site_feed import SiteFeed

__all__ = ["SiteFeed"]
