"""The models whose power trustlab simulates, by name (standard library only).

Kept apart from :mod:`analysis.power_simulation` (SciPy and the mixed-model code) so that
``trustlab power`` can check ``--model`` before it knows whether it will simulate at all: an
analytic answer imports neither (issue 49). :mod:`analysis.power_simulation` re-exports both.
"""

from __future__ import annotations

__all__ = ["SIMULATED_MODELS", "SIMULATED_MODEL_NAMES"]

SIMULATED_MODELS: dict[str, str] = {
    "lmm": "rating ~ condition * session + (1 | participant), REML, Satterthwaite df",
    "ordinal": "rating ~ condition * session, proportional odds (cumulative logit), Wald chi2 "
    "with participant-clustered SEs; data from a random-intercept latent logistic model",
}
"""The models whose power is simulated (``trustlab power --model``), as each result names it."""

SIMULATED_MODEL_NAMES: dict[str, str] = {"lmm": "mixed model", "ordinal": "ordinal model"}
"""Short names of :data:`SIMULATED_MODELS` for sentences and legends."""
