"""The staff roles, apart from the tables that store them.

An enumeration of the standard library only, so that ``trustlab user create --help`` can offer
the roles as choices without loading the database layer (app.tables re-exports it, for everything
else)."""

from __future__ import annotations

from enum import StrEnum


class Role(StrEnum):
    """What a signed-in person may do: admin ⊇ experimenter and analyst rights."""

    ADMIN = "admin"
    EXPERIMENTER = "experimenter"
    ANALYST = "analyst"
