"""The analysis texts on small and odd samples (issue 21, defect 7): one participant, one
condition, a self-described gender, a post-study questionnaire, reverse-scored items."""

from __future__ import annotations

from analysis.instruments import DEFAULT_INSTRUMENTS, InstrumentSpec, ItemSpec
from analysis.methods import design_paragraph, participants_paragraph
from analysis.prose import count, gender_word, item_title, value_range
from analysis.synthetic import SEED_PAPER_PROTOCOL


def test_the_pieces() -> None:
    assert count(1, "participant") == "1 participant" and count(0, "participant").endswith("s")
    assert count(2, "category") == "2 categories"
    assert (
        item_title("I perceive the robot as trustworthy.") == "I perceive the robot as trustworthy"
    )
    assert item_title("The robot questioned my answers.", reverse_keyed=True) == (
        "The robot questioned my answers (reverse-scored)"
    )
    assert value_range(34, 34, "years") == "34 years" and value_range(22, 48) == "22–48"
    assert gender_word("Female") == "female"
    assert gender_word("I describe myself as…") == "self-described"
    assert gender_word("Prefer not to say") == "not stated"


def test_one_participant_who_describes_their_own_gender() -> None:
    sample = {
        "n": 1,
        "by_condition": {"C2": 1},
        "gender": {"I describe myself as…": 1},
        "age": {"n": 1, "mean": 34.0, "sd": float("nan"), "min": 34.0, "max": 34.0},
    }
    text = participants_paragraph(SEED_PAPER_PROTOCOL, sample)
    assert text.startswith("N = 1 participant was analysed (C1, Exp3: 0; C2, meta-learned")
    assert "1 self-described; aged 34 years (M = 34.00)." in text
    assert "i describe" not in text and "34–34" not in text


def test_a_post_study_questionnaire_is_said_to_come_after() -> None:
    post = InstrumentSpec(
        "post",
        "After the study",
        (ItemSpec("overall_experience", "Overall, how was it?", "likert", minimum=1, maximum=5),),
        after_study=True,
    )
    text = design_paragraph(SEED_PAPER_PROTOCOL, (*DEFAULT_INSTRUMENTS, post))
    before = text[text.index("Before the study") :]
    assert "After the study" not in before.split(".")[0]
    assert "After the last session they completed: After the study." in text
