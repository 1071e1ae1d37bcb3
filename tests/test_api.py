"""The front door (hammer/api.py): the README's library example runs as it stands, from a folder of
its own, and the names load only when used."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest

from tests.runtime_helpers import ENV, ROOT

pytestmark = pytest.mark.timeout(400)


def _readme_block() -> str:
    text = (ROOT / "README.md").read_text()
    section = text[text.index("### As a library"):]
    return re.search(r"```python\n(.*?)```", section, re.DOTALL).group(1)


def test_the_readme_library_example_runs_as_written(tmp_path):
    code = _readme_block()
    assert "hammer.train(" in code and "hammer.up(" in code and "hammer.serve_bundle(" in code
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=ENV, capture_output=True, text=True,
                       timeout=360, check=False)
    assert r.returncode == 0, r.stderr[-3000:]
    first, last = r.stdout.strip().splitlines()[-2:]
    metric, rows = first.split()
    assert float(metric) < 0 and rows == "64"  # cooperative navigation's metric is a negative distance cost
    assert last == "True False"
    assert (tmp_path / "bundles" / "lib-cn3" / "manifest.json").is_file()


def test_importing_hammer_loads_nothing_until_a_name_is_used():
    probe = ("import sys, hammer; before = sorted(m for m in sys.modules if m.startswith('hammer')); "
             "c = hammer.config('cn3', variant='il', episodes=10); "
             "print(before, c.variant, c.episodes, 'hammer.api' in sys.modules)")
    r = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, env=ENV, cwd=ROOT, check=True)
    assert r.stdout.strip() == "['hammer'] il 10 True"


def test_a_wrong_field_names_itself():
    import hammer

    with pytest.raises(hammer.ConfigError, match="gama"):
        hammer.config("cn3", gama=0.9)
    with pytest.raises(AttributeError, match="no attribute 'trian'"):
        hammer.trian  # noqa: B018
