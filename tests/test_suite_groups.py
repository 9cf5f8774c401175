"""``make test`` runs the tests marked ``measure`` on one pytest-xdist worker (``--dist
loadgroup``, tests/conftest.py), never beside one another."""

import pytest


@pytest.mark.measure
def test_a_measure_test_runs_in_the_measure_group(request):
    """The group is the suffix pytest-xdist gives a test's node id on its worker: 3.8 writes
    it where pytest 9.2 no longer reads it (pytest-dev/pytest-xdist#1386: every test then
    went to any worker, the measurements side by side), so pytest is held below 9.2
    (pyproject.toml)."""
    if getattr(request.config, "workerinput", None) is None or not request.config.getvalue("loadgroup"):
        pytest.skip("not on a pytest-xdist worker under --dist loadgroup")
    assert request.node.nodeid.endswith("@measure"), request.node.nodeid
