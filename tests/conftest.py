"""The session's set-up: peers installed first, then the files marked ``slow`` run first.

Before any test runs, the controller makes the peers the selected tests pair
with present (:mod:`peers`: installed as root, else one line and a non-zero
exit).

The suite runs on every core with one test file per worker (``--dist loadfile``
in pyproject.toml); the workers take files in collection order, so a slow file
collected last would run alone at the end while the other workers sit idle.
Starting the slow files first lets the short ones fill in around them.
"""

from __future__ import annotations

import peers
import pytest


def pytest_configure(config: pytest.Config) -> None:
    peers.check(config)  # the controller only; a worker returns at once


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    slow_files = {item.path for item in items if item.get_closest_marker("slow") is not None}
    items.sort(key=lambda item: item.path not in slow_files)  # stable: order kept within each
