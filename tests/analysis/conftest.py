"""Shared fixtures of the analysis tests."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

DATA = Path(__file__).parent / "data"
REFERENCE = DATA / "reference_anova"
"""Copy of shared/reference/anova (README, CSVs, expected JSON, R afex/car JSON)."""


def load_reference(case: str) -> tuple[pd.DataFrame, dict[str, Any], dict[str, Any]]:
    """CSV, expected.json and r/<case>.json of a reference case."""
    data = pd.read_csv(REFERENCE / f"{case}.csv")
    expected = json.loads((REFERENCE / f"{case}.expected.json").read_text())
    r_values = json.loads((REFERENCE / "r" / f"{case}.json").read_text())
    return data, expected, r_values


@pytest.fixture
def dropouts() -> pd.DataFrame:
    """2 (C1 n=11, C2 n=14) × 4 sessions with three incomplete participants."""
    return pd.read_csv(DATA / "mixed_2x4_dropouts.csv")


def make_mixed(
    sizes: tuple[int, ...],
    n_levels: int,
    seed: int = 0,
    effect: float = 0.5,
) -> pd.DataFrame:
    """Random long mixed-design data with the given group sizes (for edge cases)."""
    rng = np.random.default_rng(seed)
    rows = []
    subject = 0
    for g, n in enumerate(sizes):
        for _ in range(n):
            subject += 1
            base = rng.normal(0, 1)
            for s in range(n_levels):
                value = base + effect * g * s + rng.normal(0, 1)
                rows.append((subject, f"G{g + 1}", s + 1, value))
    return pd.DataFrame(rows, columns=["subject", "group", "time", "y"])
