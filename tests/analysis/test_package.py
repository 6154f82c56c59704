"""The package's statistics core is imported on first use (analysis/__init__.py)."""

from __future__ import annotations

import analysis


def test_every_exported_name_resolves_from_its_home() -> None:
    assert sorted(analysis._HOMES) == sorted(analysis.__all__)
    for name in analysis.__all__:
        assert getattr(analysis, name) is not None, name
