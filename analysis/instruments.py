"""Questionnaire instruments as data: items, response scales, value labels and reverse keys.

A study protocol may translate or adapt an instrument, so nothing in the scoring, codebook or
SPSS export hard-codes an item: they all read these specifications. The defaults reproduce the
published instruments of the seed paper's protocol (see ``shared/reference/instruments.md``);
the app builds its own from the protocol and passes them in.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

from analysis.errors import InvalidInputError

__all__ = [
    "BACKGROUND",
    "DEFAULT_INSTRUMENTS",
    "DEMOGRAPHICS",
    "NARS",
    "TIPI",
    "TRUST",
    "InstrumentSpec",
    "ItemKind",
    "ItemSpec",
    "likert_instrument",
]

ItemKind = Literal["likert", "numeric", "categorical", "text"]


@dataclass(frozen=True)
class ItemSpec:
    """One questionnaire item as stored and exported.

    Attributes
    ----------
    key : str
        Stored item key, unique within the study (e.g. ``"tipi_1"``); it becomes the column name
        in the wide export, so it should be a valid SPSS/JASP name.
    text : str
        Wording as presented to participants (the adapted text, if the study adapted it).
    kind : {"likert", "numeric", "categorical", "text"}
        Likert and numeric items are numbers checked against ``minimum``/``maximum``;
        categorical items are codes (numbers or strings) with ``value_labels``; text is free text.
    minimum, maximum : float or None
        Allowed range of numeric answers (inclusive).
    value_labels : tuple of (code, label)
        Labels of the response options (Likert anchors, category names).
    reverse : bool
        Reverse-keyed: its scored value is ``minimum + maximum − value``.
    expected : str or None
        An attention check's expected answer: the item tells whether a participant read the
        page, so it is exported but never analysed as an outcome (:attr:`is_measure`).
    """

    key: str
    text: str
    kind: ItemKind = "likert"
    minimum: float | None = None
    maximum: float | None = None
    value_labels: tuple[tuple[int | str, str], ...] = ()
    reverse: bool = False
    expected: str | None = None

    @property
    def is_measure(self) -> bool:
        """Whether the analysis treats its answers as a measure (a rating or a number that is
        not an attention check)."""
        return self.kind in ("likert", "numeric") and self.expected is None

    def __post_init__(self) -> None:
        if not self.key:
            raise InvalidInputError("an item needs a non-empty key")
        if self.kind not in ("likert", "numeric", "categorical", "text"):
            raise InvalidInputError(f"item {self.key!r}: unknown kind {self.kind!r}")
        if self.kind == "likert" and (self.minimum is None or self.maximum is None):
            raise InvalidInputError(f"Likert item {self.key!r} needs minimum and maximum")
        if (
            self.minimum is not None
            and self.maximum is not None
            and not self.minimum < self.maximum
        ):
            raise InvalidInputError(f"item {self.key!r}: minimum must be below maximum")
        if self.reverse and (self.minimum is None or self.maximum is None):
            raise InvalidInputError(f"reverse-keyed item {self.key!r} needs minimum and maximum")

    def scored(self, value: float) -> float:
        """The value after applying the reverse key (unchanged if not reverse-keyed)."""
        if self.reverse:
            low, high = self.minimum, self.maximum
            if low is None or high is None:  # unreachable: checked in __post_init__
                raise InvalidInputError(f"reverse-keyed item {self.key!r} needs a range")
            return low + high - value
        return value


@dataclass(frozen=True)
class InstrumentSpec:
    """A questionnaire: its items, when it is given, and where it comes from.

    Attributes
    ----------
    name : str
        Stored instrument key (``"tipi"``, ``"nars"``, ``"trust"``…).
    label : str
        Human-readable name.
    items : tuple of ItemSpec
    per_session : bool
        Answered after every session (stored with a session number) rather than once.
    after_study : bool
        Answered once after the last session (the Methods say "after", not "before").
    citation : str
        Source of the instrument (exported in the codebook).
    stem : str
        Instruction shown above the items.
    """

    name: str
    label: str
    items: tuple[ItemSpec, ...]
    per_session: bool = False
    after_study: bool = False
    citation: str = ""
    stem: str = ""
    _by_key: Mapping[str, ItemSpec] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        keys = [item.key for item in self.items]
        if not keys:
            raise InvalidInputError(f"instrument {self.name!r} has no items")
        dup = sorted({k for k in keys if keys.count(k) > 1})
        if dup:
            raise InvalidInputError(f"instrument {self.name!r} lists item(s) {dup} twice")
        object.__setattr__(self, "_by_key", {item.key: item for item in self.items})

    @property
    def item_keys(self) -> tuple[str, ...]:
        """Item keys in presentation order."""
        return tuple(item.key for item in self.items)

    @property
    def reverse(self) -> frozenset[str]:
        """Keys of the reverse-keyed items."""
        return frozenset(item.key for item in self.items if item.reverse)

    def item(self, key: str) -> ItemSpec:
        """The item with this key (``InvalidInputError`` if the instrument has none)."""
        try:
            return self._by_key[key]
        except KeyError:
            raise InvalidInputError(f"instrument {self.name!r} has no item {key!r}") from None


def likert_instrument(
    name: str,
    label: str,
    texts: Sequence[str],
    *,
    scale_min: int,
    scale_max: int,
    anchors: Mapping[int, str] | None = None,
    reverse: Iterable[int] = (),
    per_session: bool = False,
    citation: str = "",
    stem: str = "",
    key_prefix: str | None = None,
) -> InstrumentSpec:
    """Build a Likert instrument whose items are keyed ``<prefix>_1`` … ``<prefix>_n``.

    ``reverse`` lists 1-based item numbers that are reverse-keyed.
    """
    prefix = key_prefix or name
    reverse_numbers = set(reverse)
    unknown = sorted(n for n in reverse_numbers if not 1 <= n <= len(texts))
    if unknown:
        raise InvalidInputError(f"instrument {name!r}: reverse item number(s) {unknown} unknown")
    labels = tuple(sorted((anchors or {}).items()))
    items = tuple(
        ItemSpec(
            key=f"{prefix}_{i}",
            text=text,
            kind="likert",
            minimum=scale_min,
            maximum=scale_max,
            value_labels=labels,
            reverse=i in reverse_numbers,
        )
        for i, text in enumerate(texts, start=1)
    )
    return InstrumentSpec(
        name=name, label=label, items=items, per_session=per_session, citation=citation, stem=stem
    )


_AGREE_5 = {
    1: "Strongly disagree",
    2: "Disagree",
    3: "Neither agree nor disagree",
    4: "Agree",
    5: "Strongly agree",
}
_AGREE_7 = {
    1: "Disagree strongly",
    2: "Disagree moderately",
    3: "Disagree a little",
    4: "Neither agree nor disagree",
    5: "Agree a little",
    6: "Agree moderately",
    7: "Agree strongly",
}

TIPI = likert_instrument(
    "tipi",
    "Ten-Item Personality Inventory (TIPI)",
    [
        "Extraverted, enthusiastic.",
        "Critical, quarrelsome.",
        "Dependable, self-disciplined.",
        "Anxious, easily upset.",
        "Open to new experiences, complex.",
        "Reserved, quiet.",
        "Sympathetic, warm.",
        "Disorganized, careless.",
        "Calm, emotionally stable.",
        "Conventional, uncreative.",
    ],
    scale_min=1,
    scale_max=7,
    anchors=_AGREE_7,
    reverse=(2, 4, 6, 8, 10),
    stem="I see myself as:",
    citation=(
        "Gosling, S. D., Rentfrow, P. J., & Swann, W. B. (2003). A very brief measure of the "
        "Big-Five personality domains. Journal of Research in Personality, 37, 504–528."
    ),
)
"""TIPI, 7-point; items 2, 4, 6, 8, 10 reverse-keyed (8 − x)."""

NARS = likert_instrument(
    "nars",
    "Negative Attitudes toward Robots Scale (NARS)",
    [
        "I would feel uneasy if robots really had emotions.",
        "Something bad might happen if robots developed into living beings.",
        "I would feel relaxed talking with robots.",
        "I would feel uneasy if I was given a job where I had to use robots.",
        "If robots had emotions I would be able to make friends with them.",
        "I feel comforted being with robots that have emotions.",
        'The word "robot" means nothing to me.',
        "I would feel nervous operating a robot in front of other people.",
        "I would hate the idea that robots or artificial intelligences were making judgements "
        "about things.",
        "I would feel very nervous just standing in front of a robot.",
        "I feel that if I depend on robots too much, something bad might happen.",
        "I would feel paranoid talking with a robot.",
        "I am concerned that robots would be a bad influence on children.",
        "I feel that in the future society will be dominated by robots.",
    ],
    scale_min=1,
    scale_max=5,
    anchors=_AGREE_5,
    reverse=(3, 5, 6),
    citation=(
        "Nomura, T., Suzuki, T., Kanda, T., & Kato, K. (2006). Measurement of negative attitudes "
        "toward robots. Interaction Studies, 7(3), 437–454. English version: Syrdal, D. S., "
        "Dautenhahn, K., Koay, K. L., & Walters, M. L. (2009)."
    ),
)
"""NARS, 5-point; items 3, 5, 6 reverse-keyed (6 − x)."""

TRUST = likert_instrument(
    "trust",
    "Per-session bi-directional trust",
    [
        "I perceive the robot as trustworthy.",
        "The robot perceives me as trustworthy.",
        "The robot anticipates my needs.",
        "The robot believed my answers.",
        "The robot questioned my answers.",
    ],
    scale_min=1,
    scale_max=5,
    anchors=_AGREE_5,
    reverse=(5,),
    per_session=True,
    citation=(
        "Gao, Sibirtseva, Castellano & Kragic, Fast Adaptation with Meta-Reinforcement Learning "
        "for Trust Modelling in Human-Robot Interaction; adapted from Salem et al. (2015) and "
        "the Propensity to Trust survey (Evans & Revelle, 2008)."
    ),
)
"""Five trust items after every session, 5-point; item 5 reverse-keyed (6 − x)."""

_VERY_5 = {1: "Very little", 2: "Little", 3: "Moderately", 4: "Much", 5: "Very much"}

BACKGROUND = InstrumentSpec(
    name="background",
    label="Background",
    items=tuple(
        ItemSpec(key, text, "likert", 1, 5, tuple(sorted(_VERY_5.items())))
        for key, text in (
            ("bg_robot_experience", "Experience interacting with robots"),
            ("bg_vr_familiarity", "Familiarity with virtual or augmented reality"),
            ("bg_digital_skills", "Skills with digital technologies"),
        )
    ),
    citation="Gao et al. (seed paper), pre-study questionnaire.",
)
"""Three 5-point background items of the seed paper."""

DEMOGRAPHICS = InstrumentSpec(
    name="demographics",
    label="Demographics",
    items=(
        ItemSpec("age", "Age (years)", "numeric", 18, 99),
        ItemSpec(
            "gender",
            "Gender",
            "categorical",
            value_labels=(
                (1, "Female"),
                (2, "Male"),
                (3, "Self-described"),
                (4, "Prefer not to say"),
            ),
        ),
    ),
)
"""Age (18–99) and gender (coded 1–4 by default; the protocol may define other codes)."""

DEFAULT_INSTRUMENTS: tuple[InstrumentSpec, ...] = (DEMOGRAPHICS, BACKGROUND, TIPI, NARS, TRUST)
"""The seed paper's instruments, in questionnaire order."""
