"""Fixtures of the bridge tests: the lab's app served on loopback, and a participant seated."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from tests.conftest import Lab
from tests.robots.harness import served


@pytest.fixture
def url(lab: Lab) -> Iterator[str]:
    """The lab's app served on a loopback port, for bridges to connect to."""
    with served(lab.app) as address:
        yield address


@pytest.fixture
def seated(lab: Lab) -> Lab:
    """P001 seated at lab-1 with session 1 started."""
    lab.enrol_and_assign("P001")
    lab.start_session()
    return lab
