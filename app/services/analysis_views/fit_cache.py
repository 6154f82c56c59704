"""Fitted analyses kept by what they depend on: in memory, and in the database for every worker
and the next start (issue 49).

A result is named by a :class:`FitKey`: the study, the kind and settings
(app.services.analysis_views.fitted), the **data version** and the **code version**.

- The data version is the SHA-256 of the scoped dataset as :func:`study_data.load_dataset` reads
  it (its manifest's ``data_sha256``: every participant row, answer, rating and step, so a new
  answer, a withdrawal or an exclusion makes a new version), with what else an analysis reads
  from the dataset: the protocol's hash and summary, the blinding state, the registration,
  and the participant codes as given (a pseudonymised export's are keyed hashes).
  Loading the dataset is what each request pays (0.2-0.3 s at 100 participants, measured in
  docs/performance.md); no version stamp kept beside the data can drift from it.
- The code version is the SHA-256 of the analysis package's source and of the module that says
  what is fitted, so a release that changes a number never serves the old one.

The key never changes meaning, so a row is written once and never updated; a new version
simply asks for another key. The database is the truth: a copy in memory is used only while its
row is still there (one indexed read), so an erasure, which deletes every row of the study
(app.services.privacy.personal_data), reaches every worker's memory at once.

Payloads are pickles made here (the rows are written by trustlab only, never by a user). The
statistics keep patsy's description of each design on the fit, which cannot be pickled and is
needed only while fitting: it is left out (:func:`dumps`).
"""

from __future__ import annotations

import hashlib
import json
import pickle
import threading
import zlib
from collections import OrderedDict
from collections.abc import Mapping
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Any

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

import analysis
from analysis.dataset import StudyDataset
from app.db import Database
from app.services.analysis_views import fitted
from app.tables import FittedAnalysis, Participant

MEMORY_ENTRIES = 64
"""Results kept in memory per process (the least recently used goes first)."""


@cache
def code_version() -> str:
    """The SHA-256 of the analysis package's source and of app.services.analysis_views.fitted."""
    digest = hashlib.sha256()
    root = Path(analysis.__file__).parent
    for path in sorted(root.rglob("*.py")):
        digest.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes())
    digest.update(Path(fitted.__file__).read_bytes())
    return digest.hexdigest()


def data_version(dataset: StudyDataset) -> str:
    """What an analysis of ``dataset`` depends on besides the code, as one SHA-256."""
    manifest = dataset.manifest
    # The codes as given: a pseudonymised dataset (app.services.privacy.pseudonyms) keeps the
    # manifest's data_sha256 of the data under their real codes.
    codes = "\n".join(dataset.participants["participant"].astype(str))
    stamp = {
        "data": manifest["data_sha256"],
        "codes": hashlib.sha256(codes.encode()).hexdigest(),
        "protocol": manifest["protocol_sha256"],
        "summary": dataset.protocol,
        "withheld": dataset.steps_withheld,
        "registration": dataset.registration,
        "registration_source": dataset.registration_source,
    }
    text = json.dumps(stamp, sort_keys=True, default=str, ensure_ascii=False)
    return hashlib.sha256(text.encode()).hexdigest()


@dataclass(frozen=True)
class FitKey:
    """Everything a fitted result depends on."""

    study_id: int
    kind: fitted.Kind
    settings: str
    """Canonical JSON of the settings (:func:`fitted.settings_of`)."""
    data_version: str
    code_version: str

    @classmethod
    def of(
        cls, *, study_id: int, kind: fitted.Kind, dataset: StudyDataset, settings: Mapping[str, Any]
    ) -> FitKey:
        """The key of ``kind`` with ``settings`` for this study's ``dataset``."""
        return cls(
            study_id,
            kind,
            json.dumps(dict(settings), sort_keys=True, separators=(",", ":")),
            data_version(dataset),
            code_version(),
        )

    @property
    def digest(self) -> str:
        """The row's ``key``: SHA-256 of the whole key."""
        text = json.dumps(
            [self.study_id, self.kind, self.settings, self.data_version, self.code_version]
        )
        return hashlib.sha256(text.encode()).hexdigest()


def _nothing() -> None:
    return None


class _Pickler(pickle.Pickler):
    """Pickles a result, leaving out patsy's design descriptions (``MixedModelFit.design_info``:
    needed while fitting only, and patsy refuses to be pickled)."""

    def reducer_override(self, obj: Any) -> Any:
        if type(obj).__module__.partition(".")[0] == "patsy":
            return _nothing, ()
        return NotImplemented


def dumps(value: Any) -> bytes:
    """A result as the bytes stored (a compressed pickle)."""
    buffer = _Buffer()
    _Pickler(buffer, protocol=pickle.HIGHEST_PROTOCOL).dump(value)
    return zlib.compress(buffer.getvalue(), 1)


def loads(payload: bytes) -> Any:
    """A result from its stored bytes."""
    return pickle.loads(zlib.decompress(payload))  # written by trustlab only


class _Buffer:
    def __init__(self) -> None:
        self._parts: list[bytes] = []

    def write(self, data: bytes) -> int:
        self._parts.append(bytes(data))
        return len(data)

    def getvalue(self) -> bytes:
        return b"".join(self._parts)


class FitCache:
    """The results of one process, over the database's: :meth:`lookup`, :meth:`store`."""

    def __init__(self, entries: int = MEMORY_ENTRIES) -> None:
        self._entries = entries
        self._memory: OrderedDict[str, Any] = OrderedDict()
        self._lock = threading.Lock()
        self.loaded = 0
        """How many results were read from the database (for tests and benchmarks)."""

    def lookup(self, db: Session, key: FitKey) -> tuple[bool, Any]:
        """``(True, result)`` when ``key``'s result is stored, else ``(False, None)``; read in
        ``db``'s transaction."""
        digest = key.digest
        with self._lock:
            held = digest in self._memory
            value = self._memory.get(digest)
        if held:
            if db.scalar(select(FittedAnalysis.id).where(FittedAnalysis.key == digest)) is None:
                self._forget(digest)  # erased since: the row went, the copy goes
                return False, None
            self._remember(digest, value)
            return True, value
        payload = db.scalar(select(FittedAnalysis.payload).where(FittedAnalysis.key == digest))
        if payload is None:
            return False, None
        value = loads(payload)
        self.loaded += 1
        self._remember(digest, value)
        return True, value

    def store(
        self,
        database: Database,
        key: FitKey,
        payload: bytes,
        *,
        seconds: float,
        since: Any,
    ) -> bool:
        """Keep a result fitted from data read at ``since`` (UTC): in the database (once: a
        worker that stored it first wins) and in memory. Refused (False) when one of the study's
        participants was erased or anonymised since: the result may hold their data."""
        with database.write_session() as db:
            changed = db.scalar(
                select(Participant.id).where(
                    Participant.study_id == key.study_id,
                    (Participant.erased_at >= since) | (Participant.anonymised_at >= since),
                )
            )
            if changed is not None:
                return False
            exists = db.scalar(select(FittedAnalysis.id).where(FittedAnalysis.key == key.digest))
            if exists is None:
                db.add(
                    FittedAnalysis(
                        study_id=key.study_id,
                        key=key.digest,
                        kind=key.kind,
                        settings=key.settings,
                        data_version=key.data_version,
                        code_version=key.code_version,
                        payload=payload,
                        seconds=seconds,
                    )
                )
                try:
                    db.commit()
                except IntegrityError:  # another worker stored it first: the same result
                    db.rollback()
        self._remember(key.digest, loads(payload))
        return True

    def _remember(self, digest: str, value: Any) -> None:
        with self._lock:
            self._memory[digest] = value
            self._memory.move_to_end(digest)
            while len(self._memory) > self._entries:
                self._memory.popitem(last=False)

    def _forget(self, digest: str) -> None:
        with self._lock:
            self._memory.pop(digest, None)
