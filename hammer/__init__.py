"""hammer: a central agent that learns to message many lightweight local RL agents (HAMMER).

`import hammer` is the front door of the library (hammer/api.py): `hammer.train`, `hammer.up`,
`hammer.export`, `hammer.serve_bundle`, `hammer.load_bundle`, `hammer.config`, `hammer.Bundle`. They load
on first use, so importing any part of hammer (every module imports this package first) costs
nothing, and an edge device that never calls them never loads them.
"""

import os as _os

__version__ = "0.1.0"

# Installed from a wheel this folder holds every part, `hammer/protocol/...` (pyproject's package-dir).
# In the repository it holds only the modules above, and the parts are the folders beside it: run from
# the repository's root (pytest, `python -m hammer` there) or through the editable install's link tree
# (build/__editable__.*, which links this file), the parts are taken from the checkout itself, so a
# module added there is found at once.
_here = _os.path.dirname(_os.path.realpath(__file__))
_root = _os.path.dirname(_here)
if not _os.path.isdir(_os.path.join(_here, "protocol")) and _os.path.isfile(_os.path.join(_root, "pyproject.toml")):
    __path__[:] = [_here, _root]
del _here, _root

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
