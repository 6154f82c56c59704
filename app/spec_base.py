"""The base of every protocol table's model: strict and frozen.

The protocol (app/protocol.py) is assembled from tables defined beside the features they
configure (the room in app/room.py, online studies in app/online/spec.py, data quality in
app/quality.py); they share this base so that a misspelt key is refused the same way everywhere
and a loaded protocol can never be changed in place.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict


class StrictSpec(BaseModel):
    """A protocol table: unknown keys are refused, and its values are frozen once validated."""

    model_config = ConfigDict(extra="forbid", frozen=True)
