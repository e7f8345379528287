"""The README's test command runs on two pytest-xdist workers with `--dist loadgroup`, and
tests/conftest.py groups tests that must share a worker (the peers' tests; a module's tests that
share a flight or a browser). pytest-xdist tags a grouped test's id with `@group`; when a pytest
release moves the id where xdist cannot tag it (pytest 9.2 with xdist 3.8), grouping stops
without a word: this test says so."""

from __future__ import annotations

import os

import pytest


@pytest.mark.xdist_group("xdist-groups-check")
def test_a_grouped_test_runs_under_its_group(request):
    if not os.environ.get("PYTEST_XDIST_WORKER") or request.config.getvalue("loadgroup") is not True:
        pytest.skip("not run by pytest-xdist with --dist loadgroup (the README's command)")
    assert request.node.nodeid.endswith("@xdist-groups-check"), (
        f"pytest-xdist did not tag {request.node.nodeid!r} with its group: tests/conftest.py's groups "
        "have no effect with this pytest / pytest-xdist pair (see the pin in pyproject.toml)")
