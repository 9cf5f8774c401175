"""What an installed (not editable) qradar holds: every package of its sources. The packages
were once listed by hand in pyproject.toml, and pipeline.dsp.cml and its kernels were not on
the list: `pip install .` made a qradar that could not import its default decoder."""

import tomllib
from pathlib import Path

from setuptools import find_packages

ROOT = Path(__file__).resolve().parents[1]
TOP = ("radar_driver", "pipeline", "replay", "experiments", "qradar")


def source_packages() -> set[str]:
    """Every folder with an ``__init__.py`` under the top-level packages, as a dotted name."""
    return {".".join(p.parent.relative_to(ROOT).parts) for top in TOP for p in (ROOT / top).rglob("__init__.py")}


def test_the_build_finds_every_package_of_the_sources():
    find = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]["find"]
    assert find.get("namespaces") is False  # no data folder (static/, scenes/) or __pycache__ as a package
    found = set(find_packages(where=str(ROOT), include=find["include"]))
    assert "pipeline.dsp.cml.kernels" in source_packages()
    assert found == source_packages(), (sorted(source_packages() - found), sorted(found - source_packages()))
