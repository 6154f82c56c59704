"""Pseudonymised exports: participant codes replaced by study-specific keyed hashes.

Data shared outside the lab (a repository, a co-author, a journal's reviewers) should not be
linkable back to the lab's records without the lab's help. A pseudonym is an HMAC-SHA256 of the
study's name and the participant's code under a key that stays on the server
(``TRUSTLAB_PSEUDONYM_KEY``): the same participant gets the same pseudonym in every export of that
study (so files can be joined), another study's pseudonyms differ, and without the key nobody can
get from a pseudonym to a code, even by trying every code (codes are short; the key is not).

What pseudonymising does not do: free-text answers and spoken transcripts are exported as they
were given, and may name people (docs/data-protection.md).
"""

from __future__ import annotations

import base64
import dataclasses
import hashlib
import hmac
from typing import TYPE_CHECKING

from app.errors import InvalidInput
from app.services.privacy import personal_data

if TYPE_CHECKING:  # named in annotations only: erasing a participant (erasure) loads no pandas
    import pandas as pd

    from analysis.dataset import StudyDataset

PREFIX = "ps-"
PSEUDONYMISED = "pseudonymised"
"""The manifest's ``participants`` value (and the codebook's wording) for such a file."""
MIN_KEY_LENGTH = 16


def require_key(key: str | None) -> bytes:
    """The configured pseudonym key; a one-line refusal when there is none (or a weak one)."""
    if not key:
        raise InvalidInput(
            "no pseudonym key is configured: set TRUSTLAB_PSEUDONYM_KEY on the server (keep it "
            "apart from the exports; docs/data-protection.md) to export with pseudonyms"
        )
    if len(key) < MIN_KEY_LENGTH:
        raise InvalidInput(
            f"TRUSTLAB_PSEUDONYM_KEY is too short to protect the codes: use at least "
            f"{MIN_KEY_LENGTH} random characters"
        )
    return key.encode()


def pseudonym(key: bytes, study: str, code: str) -> str:
    """The participant's pseudonym in this study (``ps-`` and 16 base32 characters)."""
    digest = hmac.new(key, f"{study}\x00{code}".encode(), hashlib.sha256).digest()
    return PREFIX + base64.b32encode(digest).decode("ascii")[:16].lower()


def pseudonymised(dataset: StudyDataset, *, key: bytes, study: str) -> StudyDataset:
    """The same dataset with every participant code replaced by its pseudonym in each frame the
    personal data registry exports participants' rows by (app.services.privacy.personal_data), and
    the manifest saying so (the codebook then calls the column a pseudonym)."""
    codes = dataset.participants["participant"].astype(str)
    names = {code: pseudonym(key, study, code) for code in codes}

    def renamed(frame: pd.DataFrame) -> pd.DataFrame:
        if frame.empty or "participant" not in frame.columns:
            return frame
        return frame.assign(participant=frame["participant"].astype(str).map(names))

    manifest = {**dataset.manifest, "participants": PSEUDONYMISED}
    frames = {name: renamed(getattr(dataset, name)) for name in personal_data.exported_frames()}
    return dataclasses.replace(dataset, **frames, manifest=manifest)
