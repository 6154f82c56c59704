"""Checkpoint files: hash and shape checks that name the file, and the shipped-checkpoint lookup."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from models.checkpoints import (
    HASH_FILE,
    WEIGHTS_FILE,
    load_checkpoint,
    observation_for,
    shipped_checkpoint,
)
from tests.models.conftest import make_checkpoint


def test_round_trip_is_exact(tmp_path: Path) -> None:
    written = make_checkpoint(tmp_path / "a", n_arms=5)
    loaded = load_checkpoint(tmp_path / "a" / WEIGHTS_FILE, expected_arms=5)
    assert loaded.sha256 == written.sha256
    assert loaded.n_arms == 5
    assert loaded.category == "conation"
    assert loaded.mode == "online"
    assert loaded.config == {"seed": 0}
    assert loaded.metrics == {"note": "test fixture"}
    for name, value in written.params.items():
        assert loaded.params[name].tobytes() == value.tobytes()


def test_same_content_gives_the_same_hash(tmp_path: Path) -> None:
    assert make_checkpoint(tmp_path / "a").sha256 == make_checkpoint(tmp_path / "b").sha256
    assert make_checkpoint(tmp_path / "c", seed=1).sha256 != make_checkpoint(tmp_path / "d").sha256


def test_edited_weights_are_refused_naming_the_file(tmp_path: Path) -> None:
    make_checkpoint(tmp_path / "a")
    path = tmp_path / "a" / WEIGHTS_FILE
    path.write_bytes(path.read_bytes().replace(b'"damping":0.05', b'"damping":0.06'))
    with pytest.raises(ValueError, match=f"{path}.*hash"):
        load_checkpoint(tmp_path / "a")


def test_wrong_arms_is_refused(tmp_path: Path) -> None:
    make_checkpoint(tmp_path / "a", n_arms=4)
    with pytest.raises(ValueError, match=r"4 questions.*has 3"):
        load_checkpoint(tmp_path / "a", expected_arms=3)


def _rewrite(directory: Path, **changes: object) -> None:
    """Edit weights.json and re-hash it, to reach the checks behind the hash."""
    import hashlib

    weights = json.loads((directory / WEIGHTS_FILE).read_text())
    weights.update(changes)
    data = (json.dumps(weights) + "\n").encode()
    (directory / WEIGHTS_FILE).write_bytes(data)
    (directory / HASH_FILE).write_text(hashlib.sha256(data).hexdigest() + "  weights.json\n")


def test_bad_shape_and_non_finite_numbers_are_refused(tmp_path: Path) -> None:
    make_checkpoint(tmp_path / "a")
    weights = json.loads((tmp_path / "a" / WEIGHTS_FILE).read_text())
    _rewrite(tmp_path / "a", b2=weights["b2"][:3])
    with pytest.raises(ValueError, match="'b2' has shape"):
        load_checkpoint(tmp_path / "a")
    make_checkpoint(tmp_path / "b")
    _rewrite(tmp_path / "b", step_sizes=[1.0, 1e400, 1.0])
    with pytest.raises(ValueError, match="NaN or infinite"):
        load_checkpoint(tmp_path / "b")


def test_missing_files_are_named(tmp_path: Path) -> None:
    make_checkpoint(tmp_path / "a")
    (tmp_path / "a" / HASH_FILE).unlink()
    with pytest.raises(ValueError, match=HASH_FILE):
        load_checkpoint(tmp_path / "a")
    with pytest.raises(ValueError, match="does not exist"):
        load_checkpoint(tmp_path / "nowhere")


def test_shipped_lookup_prefers_the_category_then_generic(tmp_path: Path) -> None:
    make_checkpoint(tmp_path / "online" / "conation-k4")
    make_checkpoint(tmp_path / "online" / "generic-k4")
    make_checkpoint(tmp_path / "online" / "generic-k3", n_arms=3)
    found = shipped_checkpoint(4, category="conation", directory=tmp_path)
    assert found == tmp_path / "online" / "conation-k4"
    assert shipped_checkpoint(4, category="affection", directory=tmp_path).name == "generic-k4"
    with pytest.raises(ValueError, match=r"for 7 questions.*K = 3, 4"):
        shipped_checkpoint(7, directory=tmp_path)
    with pytest.raises(ValueError, match="mode"):
        shipped_checkpoint(4, mode="offline", directory=tmp_path)


def test_observation_is_fixed_by_name_and_non_degenerate() -> None:
    a = observation_for("cognition")
    assert a.tobytes() == observation_for("cognition").tobytes()
    assert a.tobytes() != observation_for("affection").tobytes()
    assert np.linalg.norm(a) > 0.5 and np.ptp(a) > 0.1
