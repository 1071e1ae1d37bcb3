"""hammer: a central agent that learns to message many lightweight local RL agents (HAMMER).

`import hammer` is the front door of the library (hammer/api.py): `hammer.train`, `hammer.up`,
`hammer.export`, `hammer.serve_bundle`, `hammer.load_bundle`, `hammer.config`, `hammer.Bundle`. They load
on first use, so importing any part of hammer (every module imports this package first) costs
nothing, and an edge device that never calls them never loads them.
"""

import os as _os

__version__ = "0.1.0"

# Installed (a wheel, or the editable install's static link tree, pyproject's package-dir) this folder
# holds every part, `hammer/protocol/...`. In the repository itself it holds only the modules above and
# the parts are the folders beside it; when the repository's root comes first on sys.path (pytest, or
# `python -m hammer` run there) this folder is `hammer`, and its parts are found beside it.
if not _os.path.isdir(_os.path.join(_os.path.dirname(__file__), "protocol")):
    _root = _os.path.dirname(_os.path.dirname(__file__))
    if _os.path.isfile(_os.path.join(_root, "pyproject.toml")):
        __path__.append(_root)

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
