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


def test_the_inner_kernel_tests_share_a_worker(request):
    """The modules that compile cml's inner kernels on their first call exist and are grouped."""
    from conftest import INNER_KERNEL_TESTS

    here = request.path.parent
    assert all((here / f"{m}.py").exists() for m in INNER_KERNEL_TESTS), INNER_KERNEL_TESTS
    if getattr(request.config, "workerinput", None) is not None and request.config.getvalue("loadgroup"):
        names = {i.nodeid for i in request.session.items if i.module.__name__ in INNER_KERNEL_TESTS}
        assert names and all(n.endswith("@cml-inner-kernels") for n in names), sorted(names)[:3]


def test_every_test_starts_qradar_through_the_one_helper(request):
    """``qradar`` in a process of its own: ``zenoh_helpers.qradar`` or its command line
    ``zenoh_helpers.QRADAR`` (for ``Popen``), never a command line a test writes itself."""
    here = request.path.parent
    written = '"-m", ' + '"qradar"'  # (in two pieces: not a command line itself)
    own = [f"{p.name}:{i}" for p in sorted(here.glob("*.py")) if p.name != "zenoh_helpers.py"
           for i, line in enumerate(p.read_text().splitlines(), 1) if written in line]
    assert own == [], own
