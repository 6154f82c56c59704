"""``trustlab simulate adaptation`` and ``trustlab pretrain``: JSON contract, files, errors."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
import typer
from typer.testing import CliRunner, Result

from app.cli.engine import EXIT_BAD_INPUT, register
from models.checkpoints import load_checkpoint, trained_feedback, with_temperature
from models.feedback import FeedbackModel
from tests.conftest import protocol_text
from tests.models.conftest import make_checkpoint


@pytest.fixture(scope="module")
def cli() -> typer.Typer:
    app = typer.Typer()

    @app.callback()
    def main() -> None:
        """Stand-in for the trustlab app, which has many commands."""

    register(app)
    return app


@pytest.fixture
def checkpoints(tmp_path: Path) -> Path:
    """A retrained set: generic online checkpoints for K = 3 and 4."""
    make_checkpoint(tmp_path / "online" / "generic-k3", n_arms=3)
    make_checkpoint(tmp_path / "online" / "generic-k4", n_arms=4)
    return tmp_path


def run(cli: typer.Typer, *args: str) -> Result:
    return CliRunner().invoke(cli, list(args))


def one_json(result: Result) -> dict[str, Any]:
    assert result.exit_code == 0, result.stderr
    lines = result.stdout.splitlines()
    assert len(lines) == 1
    return json.loads(lines[0])


def test_simulate_json_contract(cli: typer.Typer, checkpoints: Path) -> None:
    out = one_json(
        run(
            cli,
            "simulate",
            "adaptation",
            "--arms",
            "3",
            "--iterations",
            "5",
            "--participants",
            "40",
            "--seed",
            "1",
            "--json",
            "--checkpoint-dir",
            str(checkpoints),
        )
    )
    assert set(out) == {
        "arms",
        "iterations",
        "participants",
        "participants_answer",
        "reference",
        "learners",
    }
    assert out["reference"] == "Bayes posterior"
    assert (out["arms"], out["iterations"], out["participants"]) == (3, 5, 40)
    assert list(out["learners"]) == ["exp3", "meta", "random_init", "bayes"]
    for summary in out["learners"].values():
        assert set(summary) == {
            "p_correct",
            "iterations_to_95",
            "reached_95",
            "wrong_95",
            "reply_levels",
        }
        assert list(summary["reply_levels"]) == ["low", "medium-low", "medium", "high"]
        assert abs(sum(summary["reply_levels"].values()) - 1) < 1e-9
        assert len(summary["p_correct"]) == 6
        assert 0 <= summary["iterations_to_95"] <= 6
    again = one_json(
        run(
            cli,
            "simulate",
            "adaptation",
            "--arms",
            "3",
            "--iterations",
            "5",
            "--participants",
            "40",
            "--seed",
            "1",
            "--json",
            "--checkpoint-dir",
            str(checkpoints),
        )
    )
    assert again == out


def test_simulate_participants_who_slip_and_change_their_minds(
    cli: typer.Typer, checkpoints: Path
) -> None:
    common = ["simulate", "adaptation", "--participants", "400", "--json"]
    common += ["--checkpoint-dir", str(checkpoints), "--feedback", "binary"]
    slips = one_json(run(cli, *common, "--slip", "0.1"))
    assert slips["participants_answer"] == "binary answers, slip 0.1, hazard 0"
    assert slips["reference"] == "forward filter over slips and changes"
    assert "recovered" not in slips["learners"]["bayes"]
    changed = one_json(run(cli, *common, "--hazard", "0.02", "--change-after", "6"))
    assert changed["participants_answer"].endswith("preference changes after answer 6")
    for summary in changed["learners"].values():
        assert 0 <= summary["recovered"] <= 1 and 0 <= summary["p_new_final"] <= 1
    # the exact reference knows that people change their minds, and follows them
    assert changed["learners"]["bayes"]["recovered"] > 0.85
    sets = one_json(run(cli, *common, "--acceptable", "2"))
    assert sets["participants_answer"].endswith("2 questions answered yes")
    assert sets["learners"]["bayes"]["reached_95"] > 0.95  # the set's probability reaches .95
    table = run(
        cli,
        "simulate",
        "adaptation",
        "--participants",
        "50",
        "--change-after",
        "6",
        "--checkpoint-dir",
        str(checkpoints),
    )
    assert table.exit_code == 0 and "recovered" in table.stdout and "p new final" in table.stdout


def test_simulate_out_writes_both_figures(
    cli: typer.Typer, checkpoints: Path, tmp_path: Path
) -> None:
    result = run(
        cli,
        "simulate",
        "adaptation",
        "--arms",
        "4",
        "--participants",
        "30",
        "--out",
        str(tmp_path / "figs"),
        "--checkpoint-dir",
        str(checkpoints),
    )
    assert result.exit_code == 0, result.stderr
    assert "answers to 95%" in result.stdout
    names = sorted(p.name for p in (tmp_path / "figs").iterdir())
    assert names == ["adaptation_curves.csv", "iterations_by_arms.csv", "simulation.html"]
    sweep = (tmp_path / "figs" / "iterations_by_arms.csv").read_text()
    assert "random_init" in sweep and "\n3," in sweep and "\n4," in sweep


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--arms", "7"], "no online meta-policy checkpoint for 7 questions"),
        (["--participants", "0"], "at least 1"),
        (["--gamma", "0"], "gamma"),
        (["--preferred-prior", "1,2"], "needs 4 numbers"),
        (["--checkpoint", "/nonexistent"], "does not exist"),
        (["--feedback", "likert"], "--feedback must be binary or gaussian"),
        (["--feedback", "binary", "--slip", "0.5"], "--slip / --hazard: slip rates must lie"),
        (["--hazard", "-0.1"], "--slip / --hazard: the hazard must lie in [0, 1)"),
        (["--change-after", "0"], "--change-after must be at least 1"),
        (["--acceptable", "4"], "--acceptable must be between 1 and 3"),
    ],
)
def test_simulate_bad_input_is_one_line(
    cli: typer.Typer, checkpoints: Path, args: list[str], message: str
) -> None:
    result = run(cli, "simulate", "adaptation", "--checkpoint-dir", str(checkpoints), *args)
    assert result.exit_code == EXIT_BAD_INPUT
    assert result.stderr.startswith("error: ") and message in result.stderr
    assert len(result.stderr.splitlines()) == 1


def test_simulate_refuses_a_tampered_checkpoint(cli: typer.Typer, checkpoints: Path) -> None:
    weights = checkpoints / "online" / "generic-k4" / "weights.json"
    weights.write_text(weights.read_text().replace('"damping":0.05', '"damping":0.5'))
    result = run(cli, "simulate", "adaptation", "--checkpoint-dir", str(checkpoints))
    assert result.exit_code == EXIT_BAD_INPUT
    assert str(weights) in result.stderr


def test_pretrain_tiny_run_writes_checkpoints(cli: typer.Typer, tmp_path: Path) -> None:
    out = one_json(
        run(
            cli,
            "pretrain",
            "--category",
            "affection",
            "--mode",
            "paper",
            "--arms",
            "3",
            "--meta-batches",
            "2",
            "--tasks-per-batch",
            "4",
            "--out",
            str(tmp_path),
            "--seed",
            "3",
            "--json",
        )
    )
    (entry,) = out["checkpoints"]
    assert entry["path"] == str(tmp_path / "affection-k3")
    checkpoint = load_checkpoint(tmp_path / "affection-k3", expected_arms=3)
    assert checkpoint.sha256 == entry["sha256"]
    assert checkpoint.mode == "paper" and checkpoint.rule == "gradient"
    assert checkpoint.config["seed"] == 3


def test_pretrain_refuses_to_overwrite_a_checkpoint_without_force(
    cli: typer.Typer, tmp_path: Path
) -> None:
    tiny = ("--category", "affection", "--mode", "paper", "--arms", "3", "--meta-batches", "1")
    tiny += ("--tasks-per-batch", "2", "--out", str(tmp_path), "--json")
    first = one_json(run(cli, "pretrain", *tiny, "--seed", "1"))["checkpoints"][0]
    refused = run(cli, "pretrain", *tiny, "--seed", "2")
    assert refused.exit_code == EXIT_BAD_INPUT
    assert refused.stderr.startswith("error: ") and "--force" in refused.stderr
    assert str(tmp_path / "affection-k3") in refused.stderr
    kept = load_checkpoint(tmp_path / "affection-k3", expected_arms=3)
    assert kept.sha256 == first["sha256"] and kept.config["seed"] == 1
    forced = one_json(run(cli, "pretrain", *tiny, "--seed", "2", "--force"))["checkpoints"][0]
    replaced = load_checkpoint(tmp_path / "affection-k3", expected_arms=3)
    assert replaced.sha256 == forced["sha256"] and replaced.config["seed"] == 2


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--mode", "offline"], "mode"),
        (["--objective", "accuracy"], "objective"),
        (["--arms", "1"], "arms"),
        (["--preferred-prior", "a,b,c,d"], "comma-separated"),
    ],
)
def test_pretrain_bad_input_is_one_line(
    cli: typer.Typer, tmp_path: Path, args: list[str], message: str
) -> None:
    result = run(cli, "pretrain", "--out", str(tmp_path), *args)
    assert result.exit_code == EXIT_BAD_INPUT
    assert result.stderr.startswith("error: ") and message in result.stderr


def test_pretrain_warns_when_calibration_cannot_reach_its_limit(
    cli: typer.Typer, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import models.pretrain

    def hopeless(theta: Any, layout: Any, args: Any) -> tuple[Any, dict[str, Any]]:
        trial = {"scale": 0.5, "iterations_to_95": 13.0, "wrong_95": 0.5, "mean_p_correct": 0.3}
        return theta, {"scale": 0.5, "within_limit": False, "trials": [trial]}

    monkeypatch.setattr(models.pretrain, "calibrate_step_scale", hopeless)
    monkeypatch.setattr(models.pretrain, "select_calibrated", lambda *args: None)
    result = run(
        cli,
        *("pretrain", "--category", "generic", "--arms", "3", "--meta-batches", "1"),
        *("--tasks-per-batch", "4", "--horizon", "2", "--out", str(tmp_path), "--seed", "1"),
        "--paper-feedback",  # calibration is the paper's model's selection
    )
    assert result.exit_code == 0
    assert "no step scale down to 0.5 brought wrong_95 within the calibration limit" in (
        result.stderr
    )


def test_pretrain_trains_for_the_protocols_feedback_model(cli: typer.Typer, tmp_path: Path) -> None:
    """By default the shipped protocol's model: anchored, with forgetting and surprise gates,
    scored and chosen against the exact filter; ``--paper-feedback`` trains as the replication
    set was trained."""
    tiny = ("--category", "generic", "--arms", "3", "--meta-batches", "1", "--horizon", "3")
    tiny += ("--tasks-per-batch", "4", "--validate-every", "1", "--json")
    run(cli, "pretrain", *tiny, "--out", str(tmp_path / "robust"))
    robust = load_checkpoint(tmp_path / "robust" / "generic-k3", expected_arms=3)
    model = trained_feedback(robust)
    assert model.kind == "binary" and model.hazard == 0.02 and max(model.slips) == 0.1
    assert robust.config["anchor"] and robust.config["forgetting"]
    assert robust.config["selection"] == "filter" and robust.config["bounded_baseline"]
    assert robust.config["objective"] == "filter" and not robust.remembers
    assert robust.prior is not None and robust.retention is not None
    assert robust.retention.shape == (3,) and "filter_score" in robust.metrics["validations"][0]
    run(cli, "pretrain", *tiny, "--out", str(tmp_path / "paper"), "--paper-feedback")
    paper = load_checkpoint(tmp_path / "paper" / "generic-k3", expected_arms=3)
    assert trained_feedback(paper).same_as(FeedbackModel.paper(0.1))
    assert paper.prior is None and paper.retention is None and "feedback" in paper.config
    assert paper.config["feedback"] is None and not paper.config["anchor"]
    run(cli, "pretrain", *tiny, "--out", str(tmp_path / "plain"), "--no-forgetting")
    assert load_checkpoint(tmp_path / "plain" / "generic-k3", expected_arms=3).retention is None


def test_pretrain_for_a_protocol_file_and_its_refusals(cli: typer.Typer, tmp_path: Path) -> None:
    lab = tmp_path / "lab.toml"
    lab.write_text(protocol_text(**{"hazard = 0.02": "hazard = 0.05"}), encoding="utf-8")
    tiny = ("--category", "generic", "--arms", "2", "--meta-batches", "1", "--horizon", "2")
    tiny += ("--tasks-per-batch", "4", "--validate-every", "1", "--json")
    run(cli, "pretrain", *tiny, "--out", str(tmp_path / "lab"), "--protocol", str(lab))
    trained = load_checkpoint(tmp_path / "lab" / "generic-k2", expected_arms=2)
    assert trained_feedback(trained).hazard == 0.05
    both = run(
        cli,
        "pretrain",
        *tiny,
        "--out",
        str(tmp_path / "x"),
        "--protocol",
        str(lab),
        "--paper-feedback",
    )
    assert both.exit_code == EXIT_BAD_INPUT and "exclude each other" in both.stderr
    lab.write_text(protocol_text(**{"hazard = 0.02": "hazard = -1"}), encoding="utf-8")
    bad = run(cli, "pretrain", *tiny, "--out", str(tmp_path / "y"), "--protocol", str(lab))
    assert bad.exit_code == EXIT_BAD_INPUT
    assert bad.stderr.startswith("error: ") and "learners.feedback.hazard" in bad.stderr
    assert not (tmp_path / "x").exists() and not (tmp_path / "y").exists()


def test_pretrain_defaults_give_the_gates_their_memory() -> None:
    """The shipped protocol's model trains with forgetting and gates, scored against the
    filter; the gates' memory (issue 36) only when asked, and never without the gates."""
    from app.cli.engine import training_feedback
    from models.pretrain_config import PretrainArgs

    shipped = training_feedback("online", None, False, None, None, None)
    assert shipped["forgetting"] and shipped["surprise_gates"] and not shipped["surprise_memory"]
    assert shipped["objective"] == shipped["selection"] == "filter"
    assert training_feedback("online", None, False, None, None, None, True)["surprise_memory"]
    no_gates = training_feedback("online", None, False, None, None, False)
    assert not no_gates["surprise_gates"] and not no_gates["surprise_memory"]
    assert not training_feedback("online", None, True, None, None, None)["surprise_memory"]
    lone = training_feedback("online", None, False, None, None, False, True)
    with pytest.raises(ValueError, match="needs them"):
        PretrainArgs(**lone).resolved()
    assert shipped["question_trace"] is None  # the per-question trace, likewise only when asked
    traced = training_feedback("online", None, False, None, None, None, None, "contradiction")
    assert PretrainArgs(**traced).resolved().question_trace == "contradiction"
    with pytest.raises(ValueError, match="question_trace must be one of"):
        PretrainArgs(**{**traced, "question_trace": "hunch"}).resolved()
    untraced = training_feedback("online", None, False, None, None, False, None, "surprise")
    with pytest.raises(ValueError, match="part of the surprise gates"):
        PretrainArgs(**untraced).resolved()


def test_simulate_names_a_checkpoints_temperature(cli: typer.Typer, tmp_path: Path) -> None:
    """The table says which checkpoint ran and, for a calibrated one, its temperature."""
    trained = make_checkpoint(tmp_path / "plain" / "online" / "generic-k4", n_arms=4)
    with_temperature(trained, 1.25, tmp_path / "hot" / "online" / "generic-k4", note={})
    common = ["simulate", "adaptation", "--participants", "50", "--arms", "4"]
    plain = run(cli, *common, "--checkpoint-dir", str(tmp_path / "plain"))
    hot = run(cli, *common, "--checkpoint-dir", str(tmp_path / "hot"))
    assert plain.exit_code == 0 and hot.exit_code == 0, plain.stderr + hot.stderr
    assert "temperature" not in plain.stdout.splitlines()[0]
    assert "temperature 1.25)" in hot.stdout.splitlines()[0]
