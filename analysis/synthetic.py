"""Seeded synthetic studies for demos, tests and benchmarks.

Generates a :class:`~analysis.dataset.StudyDataset` shaped like the seed paper's study (two
conditions, four sessions of three runs, three categories of four questions, TIPI, NARS and
the trust items) with a built-in condition × session effect on trust and faster adaptation in
C2. Fully vectorised so 10,000 participants take about a second; the same seed always gives
the same data.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from analysis.dataset import ProtocolSummary, StudyDataset
from analysis.errors import InvalidInputError

__all__ = ["SEED_PAPER_PROTOCOL", "synthetic_study"]

SEED_PAPER_PROTOCOL: ProtocolSummary = {
    "study": "Meta-learned adaptation and bi-directional trust",
    "conditions": [
        {
            "code": "C1",
            "label": "Exp3",
            "description": "each category's question is chosen by an Exp3 bandit",
        },
        {
            "code": "C2",
            "label": "meta-learned policy",
            "description": "each category's question is chosen by a policy-gradient bandit "
            "policy pre-trained with MAML",
        },
    ],
    "categories": {
        "conation": [
            "Do you want to escape the room?",
            "Do you come here to stay with me?",
            "Did you come here to bring me something?",
            "Did you come here to look for your friends?",
        ],
        "affection": [
            "Be careful with the walls. You should avoid them.",
            "I can help you to do whatever you want to do here.",
            "Hey, be relaxed, no matter what you do, you have no fault in this game.",
            "Are you worried? Don't worry! I am here with you.",
        ],
        "cognition": [
            "Here are the keys. Do you need the first key?",
            "Here are the keys. Do you need the second key?",
            "Here are the keys. Do you need the third key?",
            "Here are the keys. Do you need the fourth key?",
        ],
    },
    "preferred_arms": {"conation": 0, "affection": 0, "cognition": 1},
    "sessions": 4,
    "runs_per_session": 3,
    "familiarisation_runs": 1,
    "allocation": "balanced permuted blocks, concealed from the experimenter",
    "feedback": 'answer "yes" → reward 1, "no" → reward 0',
}
"""The seed paper's protocol as a summary (DESIGN.md, "The protocol")."""


def synthetic_study(
    n_participants: int = 24,
    *,
    seed: int = 0,
    with_steps: bool = True,
    dropout_rate: float = 0.0,
) -> StudyDataset:
    """A seeded synthetic study with ``n_participants`` split evenly over C1 and C2.

    Parameters
    ----------
    n_participants : int
        At least 2.
    seed : int
        Seed of :func:`numpy.random.default_rng`.
    with_steps : bool
        Also generate the step log (3 categories × 12 iterations per participant).
    dropout_rate : float
        Share of participants who stop after a random session (their later trust answers are
        missing, their status is "withdrawn" for half of them and "active" for the rest).
    """
    if n_participants < 2:
        raise InvalidInputError("a synthetic study needs at least two participants")
    rng = np.random.default_rng(seed)
    n = n_participants
    codes = np.array([f"P{i:05d}" for i in range(1, n + 1)], dtype=object)
    condition = np.where(np.arange(n) % 2 == 0, "C1", "C2").astype(object)
    is_c2 = condition == "C2"
    last_session = np.full(n, 4)
    drops = rng.random(n) < dropout_rate
    last_session[drops] = rng.integers(1, 4, drops.sum())
    status = np.where(drops, np.where(rng.random(n) < 0.5, "withdrawn", "active"), "completed")
    participants = pd.DataFrame(
        {
            "participant": codes,
            "condition": condition,
            "status": status.astype(object),
            "gender_stratum": np.where(rng.random(n) < 0.5, "female", "male").astype(object),
        }
    )

    frames = [_once_only(rng, codes), _trust(rng, codes, is_c2, last_session)]
    responses = pd.concat(frames, ignore_index=True)
    responses["session"] = responses["session"].astype("Int64")
    dataset_steps = _steps(rng, codes, condition, is_c2, last_session) if with_steps else None
    manifest = {
        "generator": "analysis.synthetic.synthetic_study",
        "seeds": {"synthetic_study": seed},
        "n_participants": n,
    }
    if dataset_steps is None:
        return StudyDataset(
            participants=participants,
            responses=responses,
            protocol=SEED_PAPER_PROTOCOL,
            manifest=manifest,
        )
    return StudyDataset(
        participants=participants,
        responses=responses,
        protocol=SEED_PAPER_PROTOCOL,
        steps=dataset_steps,
        manifest=manifest,
    )


def _long(codes: np.ndarray, instrument: str, items: list[str], values: np.ndarray) -> pd.DataFrame:
    """Long rows of a once-only instrument; ``values`` has shape (participants, items)."""
    n, k = values.shape
    return pd.DataFrame(
        {
            "participant": np.repeat(codes, k),
            "instrument": instrument,
            "session": pd.array([pd.NA] * (n * k), dtype="Int64"),
            "item": np.tile(np.array(items, dtype=object), n),
            "value": values.ravel().astype(float),
        }
    )


def _once_only(rng: np.random.Generator, codes: np.ndarray) -> pd.DataFrame:
    n = len(codes)
    age = np.clip(np.round(rng.normal(27, 5.4, n)), 18, 99)
    gender = rng.choice([1, 2, 3, 4], size=n, p=[0.46, 0.5, 0.02, 0.02])
    background = rng.integers(1, 6, (n, 3))
    tipi = np.clip(np.round(rng.normal(4.5, 1.4, (n, 10))), 1, 7)
    nars = np.clip(np.round(rng.normal(2.8, 1.0, (n, 14))), 1, 5)
    return pd.concat(
        [
            _long(codes, "demographics", ["age", "gender"], np.column_stack([age, gender])),
            _long(
                codes,
                "background",
                ["bg_robot_experience", "bg_vr_familiarity", "bg_digital_skills"],
                background,
            ),
            _long(codes, "tipi", [f"tipi_{i}" for i in range(1, 11)], tipi),
            _long(codes, "nars", [f"nars_{i}" for i in range(1, 15)], nars),
        ],
        ignore_index=True,
    )


def _trust(
    rng: np.random.Generator, codes: np.ndarray, is_c2: np.ndarray, last_session: np.ndarray
) -> pd.DataFrame:
    n = len(codes)
    sessions = np.arange(1, 5)
    person = rng.normal(0, 0.6, (n, 1, 1))
    # Trust rises over sessions in C2 and stays flat in C1 (the paper's interaction).
    trend = np.where(is_c2[:, None], 0.3 * (sessions - 1), -0.05 * (sessions - 1))[:, :, None]
    base = np.array([2.8, 2.3, 2.6, 2.9, 2.9])[None, None, :]  # items 1..5 (5 before reversal)
    latent = base + person + trend + rng.normal(0, 0.8, (n, 4, 5))
    latent[:, :, 4] = 6 - latent[:, :, 4] + rng.normal(0, 0.3, (n, 4))  # item 5 reverse-keyed
    values = np.clip(np.round(latent), 1, 5)
    keep = (sessions[None, :] <= last_session[:, None])[:, :, None] & np.ones((1, 1, 5), bool)
    participant = np.broadcast_to(codes[:, None, None], values.shape)
    session = np.broadcast_to(sessions[None, :, None], values.shape)
    item = np.broadcast_to(
        np.array([f"trust_{i}" for i in range(1, 6)], dtype=object)[None, None, :], values.shape
    )
    return pd.DataFrame(
        {
            "participant": participant[keep],
            "instrument": "trust",
            "session": session[keep],
            "item": item[keep],
            "value": values[keep],
        }
    )


def _steps(
    rng: np.random.Generator,
    codes: np.ndarray,
    condition: np.ndarray,
    is_c2: np.ndarray,
    last_session: np.ndarray,
) -> pd.DataFrame:
    categories = list(SEED_PAPER_PROTOCOL["categories"])
    preferred = SEED_PAPER_PROTOCOL["preferred_arms"]
    n, c, k, iterations = len(codes), len(categories), 4, 12
    rate = np.where(is_c2, 0.35, 0.12)[:, None, None] * rng.lognormal(0, 0.2, (n, c, 1))
    t = np.arange(iterations + 1)[None, None, :]
    p_pref = 1 - (1 - 1 / k) * np.exp(-rate * t)  # (n, c, iterations + 1)
    p_pref = np.clip(p_pref + rng.normal(0, 0.02, p_pref.shape), 0.01, 0.99)
    session_of = 1 + (np.arange(iterations) // 3)
    keep = session_of[None, None, :] <= last_session[:, None, None]
    keep = np.broadcast_to(keep, (n, c, iterations))

    def probs(p: np.ndarray, arm: int) -> np.ndarray:
        out = np.repeat(((1 - p) / (k - 1))[..., None], k, axis=-1)
        out[..., arm] = p
        return out

    before = np.empty((n, c, iterations, k))
    after = np.empty((n, c, iterations, k))
    for j, category in enumerate(categories):
        before[:, j] = probs(p_pref[:, j, :-1], preferred[category])
        after[:, j] = probs(p_pref[:, j, 1:], preferred[category])
    action = np.array([preferred[cat] for cat in categories])[None, :, None] * np.ones(
        (n, 1, iterations), int
    )
    explore = rng.random((n, c, iterations)) < 0.3
    action = np.where(explore, rng.integers(0, k, (n, c, iterations)), action)
    pref = np.array([preferred[cat] for cat in categories])[None, :, None]
    answer = action == pref
    shape = (n, c, iterations)
    return pd.DataFrame(
        {
            "participant": np.broadcast_to(codes[:, None, None], shape)[keep],
            "condition": np.broadcast_to(condition[:, None, None], shape)[keep],
            "category": np.broadcast_to(np.array(categories, dtype=object)[None, :, None], shape)[
                keep
            ],
            "session": np.broadcast_to(session_of[None, None, :], shape)[keep],
            "run": np.broadcast_to((np.arange(iterations) % 3 + 1)[None, None, :], shape)[keep],
            "iteration": np.broadcast_to(np.arange(1, iterations + 1)[None, None, :], shape)[keep],
            "action": action[keep],
            "probs_before": before[keep].tolist(),
            "probs_after": after[keep].tolist(),
            "answer": answer[keep],
            "reward": answer[keep].astype(float),
        }
    )
