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
    (tmp_path / "hammer").symlink_to(ROOT)  # run beside the clone, as `git clone ... hammer` leaves it
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=ENV, capture_output=True, text=True,
                       timeout=360, check=False)
    assert r.returncode == 0, r.stderr[-3000:]
    first, last = r.stdout.strip().splitlines()[-2:]
    metric, rows = first.split()
    assert float(metric) < 0 and rows == "64"  # cooperative navigation's metric is a negative distance cost
    assert last == "True False"
    assert (tmp_path / "bundles" / "lib-cn3" / "manifest.json").is_file()


@pytest.mark.parametrize("clone", ["symlink", "copy"])
def test_a_folder_named_hammer_in_the_current_folder_does_not_shadow_the_installed_package(tmp_path, clone):
    """`git clone ... hammer` names the clone `hammer`; from the folder that holds it, the current folder
    comes first on sys.path, and the installed package must still be the one imported."""
    import shutil

    if clone == "symlink":
        (tmp_path / "hammer").symlink_to(ROOT)
    else:  # the parts of a clone that an import could take: its top-level folders, without __init__.py
        shutil.copytree(ROOT, tmp_path / "hammer", ignore=shutil.ignore_patterns(
            ".venv", ".git", "build", "runs", "docs", "tests", "__pycache__", "*.egg-info"))
    block = _readme_block()
    imports = "\n".join(ln for ln in block.splitlines() if ln.startswith("import "))
    probe = (f"{imports}\nfrom hammer.edge import EdgeAgent\nimport hammer.protocol.keys\n"
             "c = hammer.config('cn3', variant='il', episodes=10)\n"
             "print(hammer.__file__, callable(hammer.train), callable(hammer.export), c.episodes)")
    r = subprocess.run([sys.executable, "-c", probe], cwd=tmp_path, env=ENV, capture_output=True, text=True,
                       check=False, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    where, *rest = r.stdout.split()
    assert not where.startswith(str(tmp_path)) and rest == ["True", "True", "10"], r.stdout
    r = subprocess.run([sys.executable, "-m", "hammer", "--version"], cwd=tmp_path, env=ENV, capture_output=True,
                       text=True, check=False, timeout=60)
    assert r.returncode == 0 and r.stdout.startswith("hammer "), r.stderr[-2000:]


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
