"""hammer: a central agent that learns to message many lightweight local RL agents (HAMMER).

`import hammer` is the front door of the library (hammer/api.py): `hammer.train`, `hammer.up`,
`hammer.export`, `hammer.serve_bundle`, `hammer.load_bundle`, `hammer.config`, `hammer.Bundle`. They load
on first use, so importing any part of hammer (every module imports this package first) costs
nothing, and an edge device that never calls them never loads them.
"""

__version__ = "0.1.0"

__all__ = ["Bundle", "BundleError", "ConfigError", "RunConfig", "TrainResult", "UpResult", "config", "export",
           "load_bundle", "serve_bundle", "train", "up"]
_API = frozenset(__all__)


def __getattr__(name: str):
    if name in _API:
        from hammer import api

        return getattr(api, name)
    raise AttributeError(f"module 'hammer' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *_API})
