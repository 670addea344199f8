"""A non-editable install (`pip install .`, as a Snakemake conda environment would make) finds the compute presets
and the shipped motions."""
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent

PROBE = """
import pig
from importlib.resources import files
from pig.config import ConfigError, load_preset
print(pig.__file__)
print(sorted(p.name for p in (files("pig.data") / "motions").iterdir()))
try:
    print(load_preset("test")["_path"])
except ConfigError as err:
    print(err)
"""


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """The package installed with pip from a copy of the checkout (so no build folder lands in the checkout)."""
    # Built offline with this environment's setuptools, which must read pyproject's SPDX `license`.
    pytest.importorskip("setuptools", minversion="77")
    root = tmp_path_factory.mktemp("install")
    source = root / "source"
    source.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy(REPO / name, source / name)
    shutil.copytree(REPO / "pig", source / "pig", ignore=shutil.ignore_patterns("__pycache__"))
    subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation", "--no-index",
                    "--target", str(root / "site"), str(source)], check=True, capture_output=True)
    return root / "site"


def probe(site: Path, cwd: Path) -> list[str]:
    # -P: the working directory's own pig (the checkout) must not shadow the installed copy.
    env = {**os.environ, "PYTHONPATH": str(site)}
    out = subprocess.run([sys.executable, "-P", "-c", PROBE], cwd=cwd, env=env, capture_output=True, text=True,
                         check=True)
    return out.stdout.splitlines()


def test_installed_copy_finds_presets_from_the_checkout(installed):
    module, motions, preset = probe(installed, REPO)
    assert Path(module).is_relative_to(installed)  # the installed copy, not the checkout, was imported
    assert "demo.npz" in motions
    assert Path(preset) == REPO / "config" / "presets" / "test.yaml"


def test_installed_copy_elsewhere_says_where_presets_are_sought(installed, tmp_path):
    module, _, message = probe(installed, tmp_path)
    assert Path(module).is_relative_to(installed)
    assert message == (f"unknown preset 'test': no config/presets/ in the working directory {tmp_path} or beside "
                       f"the package ({installed}); run from the pig checkout or give a path to a .yaml file")
