"""The meta-learned policy (C2): a pre-trained network that adapts to one participant per answer.

The learner starts from a checkpoint's weights and, after every answer, takes the single
policy-gradient step that meta-training optimised for (see :mod:`models.learners.mlp_policy`): with
an ``online`` checkpoint a damped natural-gradient step whose step size, damping and reward baseline
for the 1st, 2nd, … answer were meta-learned with it. There is no separate learning rate to tune;
``learning_rate`` exists only to override the learned step sizes for experiments.

Numpy only: the web app builds one of these on every answer's request path.
"""

from __future__ import annotations

import base64
import math
from pathlib import Path
from typing import Any

import numpy as np

from models.checkpoints import Checkpoint, load_checkpoint
from models.learners.base import (
    check_action,
    check_reward,
    check_state_header,
    sample_index,
)
from models.learners.mlp_policy import (
    PARAM_NAMES,
    Params,
    hidden_and_logits,
    init_params,
    param_shapes,
    probabilities,
    retain,
    softmax,
    update_params,
)

_KIND = "meta"
_VERSION = 2
"""The state format :meth:`MetaPolicyLearner.state_dict` writes.

Version 1 stored every weight as a JSON number; version 2 stores each weight array as the base64
of its little-endian float64 bytes: the same bits, but encoding ~1,300 floats as decimal text took
~0.9 ms of every C2 answer (docs/performance.md) where bytes take microseconds, and the stored
state is half the size. Both versions are read, so states stored before the change (a study's
initial states among them) restore as they always did."""
_READS = (1, 2)
_FLOAT64 = np.dtype("<f8")


def _encode(array: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(array, dtype=_FLOAT64).tobytes()).decode("ascii")


def _decode(name: str, text: object, shape: tuple[int, ...]) -> np.ndarray:
    if not isinstance(text, str):
        raise ValueError(f"{name} must be base64 text (format version 2)")
    raw = base64.b64decode(text.encode("ascii"), validate=True)
    values = np.frombuffer(raw, dtype=_FLOAT64)
    if values.size != int(np.prod(shape)):
        raise ValueError(f"{name} holds {values.size} numbers where {shape} were expected")
    return values.astype(np.float64).reshape(shape)


def plain_state(state: dict[str, Any]) -> dict[str, Any]:
    """``state`` in one form whatever its format version: no version, each weight array a flat
    list of floats. For comparisons that let the last bit of a float differ (``trustlab
    verify``), where a version 1 state must equal its version 2 rewrite.

    Raises
    ------
    ValueError
        If the weights cannot be read as numbers.
    """
    params = state.get("params")
    if state.get("version") not in _READS or not isinstance(params, dict):
        return state
    plain: dict[str, list[float]] = {}
    for name, value in params.items():
        if isinstance(value, str):
            raw = base64.b64decode(value.encode("ascii"), validate=True)
            plain[name] = np.frombuffer(raw, dtype=_FLOAT64).tolist()
        else:
            plain[name] = np.asarray(value, dtype=np.float64).ravel().tolist()
    return {**{k: v for k, v in state.items() if k != "version"}, "params": plain}


def _surprise_memory(state: dict[str, Any], checkpoint: Checkpoint) -> float:
    """The state's surprise memory: required (a finite number ≥ 0) for a checkpoint whose gates
    remember, refused for any other, so a state cannot silently drop or invent it."""
    if not checkpoint.remembers:
        if "surprise_memory" in state:
            raise ValueError("meta state has a surprise memory its checkpoint does not keep")
        return 0.0
    value = state.get("surprise_memory")
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError("meta state must record its surprise memory (a number)")
    if not (math.isfinite(value) and value >= 0):
        raise ValueError(f"meta state's surprise memory must be finite and ≥ 0, got {value!r}")
    return float(value)


def _surprise_trace(state: dict[str, Any], checkpoint: Checkpoint) -> np.ndarray:
    """The state's per-question surprise trace: required (K finite numbers ≥ 0) for a
    checkpoint whose gates trace, refused for any other, as the memory is."""
    if not checkpoint.traces:
        if "surprise_trace" in state:
            raise ValueError("meta state has a surprise trace its checkpoint does not keep")
        return np.zeros(checkpoint.n_arms)
    value = state.get("surprise_trace")
    if not isinstance(value, list) or len(value) != checkpoint.n_arms:
        raise ValueError(f"meta state must record its surprise trace ({checkpoint.n_arms} numbers)")
    if any(isinstance(v, bool) or not isinstance(v, int | float) for v in value):
        raise ValueError("meta state's surprise trace must hold numbers")
    trace = np.array(value, dtype=np.float64)
    if not (np.all(np.isfinite(trace)) and np.all(trace >= 0)):
        raise ValueError(f"meta state's surprise trace must be finite and ≥ 0, got {value!r}")
    return trace


class MetaPolicyLearner:
    """One participant's copy of a meta-learned policy.

    Parameters
    ----------
    checkpoint
        A verified checkpoint (:func:`models.checkpoints.load_checkpoint`).
    learning_rate
        If given, every answer's step size is this instead of the meta-learned ones.
    params
        Starting weights; the checkpoint's when omitted (``random_init`` passes a fresh draw).
    """

    def __init__(
        self,
        checkpoint: Checkpoint,
        *,
        learning_rate: float | None = None,
        params: Params | None = None,
    ) -> None:
        if learning_rate is not None and not (np.isfinite(learning_rate) and learning_rate > 0):
            raise ValueError(f"learning_rate must be a positive number, got {learning_rate!r}")
        self.checkpoint = checkpoint
        self.n_arms = checkpoint.n_arms
        self.learning_rate = None if learning_rate is None else float(learning_rate)
        self._random = params is not None
        start = checkpoint.params if params is None else params
        self._set_initial({name: np.array(start[name], dtype=np.float64) for name in start})
        self._params: Params = dict(self._initial)
        self._answers = 0
        self._memory = 0.0
        self._trace = np.zeros(self.n_arms)

    def _set_initial(self, initial: Params) -> None:
        self._initial = initial
        self._offset = self.checkpoint.offset_for(initial, random_init=self._random)

    @classmethod
    def from_checkpoint(
        cls,
        checkpoint_or_path: Checkpoint | Path | str,
        expected_arms: int | None = None,
        *,
        learning_rate: float | None = None,
    ) -> MetaPolicyLearner:
        """A learner at the checkpoint's weights, loading (and verifying) it if given a path."""
        if isinstance(checkpoint_or_path, Checkpoint):
            checkpoint = checkpoint_or_path
            if expected_arms is not None and checkpoint.n_arms != expected_arms:
                raise ValueError(
                    f"checkpoint {checkpoint.path} is for {checkpoint.n_arms} questions, "
                    f"expected {expected_arms}"
                )
        else:
            checkpoint = load_checkpoint(checkpoint_or_path, expected_arms=expected_arms)
        return cls(checkpoint, learning_rate=learning_rate)

    @classmethod
    def random_init(cls, checkpoint: Checkpoint, rng: np.random.Generator) -> MetaPolicyLearner:
        """The same network and update rule as ``checkpoint``, from a random initialisation.

        The Appendix's comparison: what the update rule achieves without meta-learned weights.
        """
        params = init_params(
            rng, checkpoint.observation.shape[0], checkpoint.hidden, checkpoint.n_arms
        )
        return cls(checkpoint, params=params)

    @property
    def answers(self) -> int:
        """How many answers the learner has adapted to."""
        return self._answers

    def reset(self) -> None:
        """Forget every answer: back to the starting weights."""
        self._params = dict(self._initial)
        self._answers = 0
        self._memory = 0.0
        self._trace = np.zeros(self.n_arms)

    def step_size(self, answer_index: int) -> float:
        """The step size of the update after answer number ``answer_index`` (0-based), before
        a checkpoint's surprise gate scales it (:meth:`Checkpoint.step_and_retention`)."""
        if self.learning_rate is not None:
            return self.learning_rate
        sizes = self.checkpoint.step_sizes
        return float(sizes[min(answer_index, len(sizes) - 1)])

    def baseline(self, answer_index: int) -> float:
        """The reward baseline of the update after answer number ``answer_index`` (0-based)."""
        baselines = self.checkpoint.baselines
        return float(baselines[min(answer_index, len(baselines) - 1)])

    def probabilities(self) -> np.ndarray:
        """The probability of asking each question (float64, sums to one): the policy,
        calibrated by the checkpoint's temperature (:meth:`Checkpoint.calibrate`; most have
        none). What the learner asks with and what its replies and figures report."""
        c = self.checkpoint
        if c.temperature == 1.0:
            return self.policy()
        logits = hidden_and_logits(self._params, c.observation, self._offset)[1]
        return softmax(c.calibrate(logits, c.anchor_prior(random_init=self._random)))

    def policy(self) -> np.ndarray:
        """The trained policy, untempered: what its update and surprise gates were trained on
        (equal to :meth:`probabilities` for a checkpoint without a temperature)."""
        return probabilities(self._params, self.checkpoint.observation, self._offset)

    def select(self, rng: np.random.Generator) -> int:
        """Draw the next question from :meth:`probabilities` using one uniform from ``rng``."""
        return sample_index(self.probabilities(), rng)

    def update(self, action: int, reward: float) -> None:
        """Take the one-answer policy-gradient step for ``reward`` on question ``action``, then
        the checkpoint's forgetting step, if it has one.

        The reward enters raw (minus the meta-learned baseline), not clipped: meta-training saw
        the rewards of its feedback model unclipped (models/feedback.py).

        Raises
        ------
        ValueError
            If ``action`` is out of range or ``reward`` is NaN or infinite.
        """
        a = check_action(action, self.n_arms)
        r = check_reward(reward)
        # Only surprise gates need the asked question's probability: no extra forward pass else.
        # The trained policy's, not the tempered one: the gates were trained on it.
        p_asked = self.policy()[a] if self.checkpoint.gates is not None else 1.0
        parts = self.checkpoint.trace_parts(self._trace, a)
        step, retention = self.checkpoint.step_and_retention(
            self._answers, p_asked, r, self._memory, parts
        )
        memory = float(self.checkpoint.memory_after(self._memory, p_asked, r, retention))
        trace = self.checkpoint.trace_after(self._trace, a, p_asked, r, retention)
        if self.learning_rate is not None:
            step = self.learning_rate
        new = update_params(
            self._params,
            self.checkpoint.observation,
            np.asarray(a),
            np.asarray(r),
            step_size=step,
            baseline=self.baseline(self._answers),
            damping=self.checkpoint.damping,
            rule=self.checkpoint.rule,
            offset=self._offset,
        )
        if np.any(retention != 1.0):
            new = retain(new, self._initial, retention)
        if not all(np.all(np.isfinite(new[name])) for name in PARAM_NAMES):
            raise ValueError(f"update with reward {r!r} made the policy's weights non-finite")
        self._params = new
        self._answers += 1
        self._memory = memory
        self._trace = trace

    def state_dict(self) -> dict[str, Any]:
        """The learner's weights and answer count as JSON, tied to the checkpoint's hash.

        The weights are bytes in base64 (format version 2, see :data:`_VERSION`): they read back
        to the same bits. A randomly initialised learner also records its starting weights, which
        its anchor and forgetting step refer to.
        """
        state: dict[str, Any] = {
            "kind": _KIND,
            "version": _VERSION,
            "n_arms": self.n_arms,
            "checkpoint_sha256": self.checkpoint.sha256,
            "init": "random" if self._random else "checkpoint",
            "learning_rate": self.learning_rate,
            "answers": self._answers,
            "params": {name: _encode(self._params[name]) for name in PARAM_NAMES},
        }
        if self._random:
            state["initial"] = {name: _encode(self._initial[name]) for name in PARAM_NAMES}
        if self.checkpoint.remembers:  # absent for other checkpoints: their states are unchanged
            state["surprise_memory"] = self._memory
        if self.checkpoint.traces:  # likewise: only checkpoints that trace record one
            state["surprise_trace"] = [float(v) for v in self._trace]
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a state from :meth:`state_dict` of a learner on the same checkpoint.

        Raises
        ------
        ValueError
            If the state is for another kind of learner, K, checkpoint or learning rate, or its
            weights have the wrong shape or non-finite numbers.
        """
        check_state_header(state, _KIND, self.n_arms)
        version = state.get("version")
        if version not in _READS:
            raise ValueError(f"meta state version {version!r} is not one of {_READS}")
        recorded = state.get("checkpoint_sha256")
        if recorded != self.checkpoint.sha256:
            raise ValueError(
                f"meta state belongs to checkpoint sha256 {str(recorded)[:12]}…, not to "
                f"{self.checkpoint.path} (sha256 {self.checkpoint.sha256[:12]}…)"
            )
        if state.get("learning_rate") != self.learning_rate:
            raise ValueError(
                f"meta state was made with learning_rate={state.get('learning_rate')!r}, this "
                f"learner has {self.learning_rate!r}"
            )
        try:
            answers = int(state["answers"])
            raw = state["params"]
            shapes = param_shapes(
                self.checkpoint.observation.shape[0], self.checkpoint.hidden, self.n_arms
            )
            if version == 1:
                params = {name: np.asarray(raw[name], dtype=np.float64) for name in PARAM_NAMES}
            else:
                params = {name: _decode(name, raw[name], shapes[name]) for name in PARAM_NAMES}
            random = state.get("init") == "random"
            start = state.get("initial")
            if random and not isinstance(start, dict):
                raise ValueError("a randomly initialised state must record its initial weights")
            if isinstance(start, dict) and random:
                initial = {name: _decode(name, start[name], shapes[name]) for name in PARAM_NAMES}
            else:
                initial = {name: np.array(self.checkpoint.params[name]) for name in PARAM_NAMES}
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"meta state is malformed: {exc}") from None
        for name, shape in shapes.items():
            for array in (params[name], initial[name]):
                if array.shape != shape or not np.all(np.isfinite(array)):
                    raise ValueError(f"meta state: {name} must be {shape} finite numbers")
        if answers < 0:
            raise ValueError(f"meta state has a negative answer count {answers}")
        memory = _surprise_memory(state, self.checkpoint)
        trace = _surprise_trace(state, self.checkpoint)
        self._params = params
        self._answers = answers
        self._memory = memory
        self._trace = trace
        self._random = random
        self._set_initial(initial)  # after _random: a random start is anchored at uniform

    @property
    def surprise_memory(self) -> float:
        """What the learner keeps of the surprises so far (0 unless the checkpoint's gates
        remember, :class:`models.checkpoints.SurpriseGates`)."""
        return self._memory

    @property
    def surprise_trace(self) -> np.ndarray:
        """What the learner keeps of the surprises so far, per question (zeros unless the
        checkpoint's gates trace, :class:`models.checkpoints.SurpriseGates`); a copy."""
        return self._trace.copy()

    def __repr__(self) -> str:
        return (
            f"MetaPolicyLearner(n_arms={self.n_arms}, checkpoint={self.checkpoint.sha256[:12]}, "
            f"answers={self._answers})"
        )
