"""Fixtures shared by the tests that start real service processes."""

from __future__ import annotations

import os

import pytest

from tests.figures import Keeper
from tests.procs import Procs, free_port, pids_with

# Learners in tests run their update eagerly: each would otherwise compile it in the background,
# seconds of CPU that the suite's two cores need. The tests of the compiled update ask for it.
os.environ.setdefault("TPDEB_COMPILE", "off")


@pytest.fixture
def procs(tmp_path):
    """Spawns service CLIs; every one is stopped (by pid, with its group) when the test ends,
    also when it fails, and none may be left running."""
    p = Procs(tmp_path)
    yield p
    p.stop_all()
    assert not p.leftovers(), "a service outlived its test"
    assert not pids_with(str(tmp_path)), "a service process outlived its test"


@pytest.fixture
def figures(request) -> Keeper:
    """Keeps a test's measured figures as data where TPDEB_KEEP_FIGURES names a folder, with
    the run's provenance taken now, as the test begins."""
    return Keeper(request.node.nodeid)


@pytest.fixture
def endpoint():
    return f"tcp/127.0.0.1:{free_port()}"


@pytest.fixture(autouse=True)
def service_logging():
    """Services made in-process log as their process would (their lines on stdout and stderr,
    where capsys sees them); the root logger is as it was after each test."""
    import logging

    from tpdeb.services.logs import setup_logging

    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    setup_logging("info")
    yield
    root.handlers[:] = handlers
    root.setLevel(level)
