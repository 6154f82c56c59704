"""Satterthwaite degrees of freedom for the fixed effects of a linear mixed model.

Tests of fixed effects with z statistics (statsmodels' MixedLM) are too liberal with the 20–60
participants of an HRI study. lmerTest, SAS and JASP use Satterthwaite's approximation instead;
this module computes it as lmerTest does, so a PI gets the same t and F tests as R's
``lmerTest``.

For a contrast ``l``, the variance of ``l'β̂`` is ``v = l' C l`` with ``C = Var(β̂)``.
Satterthwaite's df is ``2 v² / (g' A g)`` with ``g = ∂v/∂varpar`` and ``A`` the asymptotic
covariance of the variance parameters: twice the (pseudo-)inverse of the Hessian of the REML
deviance at the estimate. F tests of several contrasts combine the single-contrast dfs as
Fai & Cornelius (1996) and lmerTest's ``contestMD`` do.

The parameterisation matters at the boundary. The df is invariant to smooth one-to-one
reparameterisations, but a variance of zero or a correlation of ±1 is where the covariance
elements stop being one: there the likelihood is not even defined on one side. lmerTest uses
``varpar = (θ, σ)``, θ the relative Cholesky factor (:mod:`analysis.reml`), in which the
likelihood is smooth across the boundary and a parameter on it contributes nothing to ``g``
(``G`` depends on it through its square): a participant variance of zero gives the df of the
model without it (ordinary least squares), as lmerTest does. So this module does the same: the
Hessian by central differences of the exact gradient of the deviance, the Jacobian of ``C``
exact, and the inverse over the positive eigenvalues of the Hessian (lmerTest's tolerance). Both
come from :class:`analysis.reml.RemlDesign`'s per-pattern sufficient statistics, so they cost
the same few milliseconds for 24 or 10,000 participants.

References
----------
Kuznetsova, Brockhoff & Christensen (2017). lmerTest package: tests in linear mixed effects
models. Journal of Statistical Software 82(13).
Fai & Cornelius (1996). Approximate F-tests of multiple degree of freedom hypotheses in
generalized least squares analyses of unbalanced split-plot experiments. J. Stat. Comput. Simul.
"""

from __future__ import annotations

import numpy as np

from analysis.reml import RemlDesign

__all__ = ["contrast_df", "f_test_df", "varpar_covariance"]

_EIGEN_TOL = 1e-8
"""Eigenvalues of the deviance Hessian at or below this are left out of its inverse (lmerTest's
``tol`` in ``as_lmerModLT``: a direction the data do not inform gets no weight)."""


def varpar_covariance(design: RemlDesign, varpar: np.ndarray) -> np.ndarray:
    """Asymptotic covariance of ``varpar = (θ, σ)``: ``2 H⁺`` with ``H`` the Hessian of the REML
    deviance (central differences of its exact gradient) and ``⁺`` the inverse over its
    positive eigenvalues, as lmerTest.

    Raises
    ------
    numpy.linalg.LinAlgError
        When the deviance is not finite around the estimate or no eigenvalue is positive.
    """
    hessian = _deviance_hessian(design, np.asarray(varpar, float))
    if not np.all(np.isfinite(hessian)):
        raise np.linalg.LinAlgError("the REML likelihood is not finite around the estimate")
    values, vectors = np.linalg.eigh(hessian)
    keep = values > _EIGEN_TOL
    if not keep.any():
        raise np.linalg.LinAlgError("the REML likelihood is flat around the estimate")
    inverse = vectors[:, keep] @ np.diag(1 / values[keep]) @ vectors[:, keep].T
    return 2 * inverse


def _deviance_hessian(design: RemlDesign, varpar: np.ndarray) -> np.ndarray:
    steps = 1e-4 * np.maximum(np.abs(varpar), 1e-2)
    hessian = np.zeros((len(varpar), len(varpar)))
    with np.errstate(all="ignore"):
        for i, step in enumerate(steps):
            shift = np.zeros(len(varpar))
            shift[i] = step
            _, up = design.deviance_and_gradient(varpar + shift)
            _, down = design.deviance_and_gradient(varpar - shift)
            hessian[i] = (up - down) / (2 * step)
    return (hessian + hessian.T) / 2


def contrast_df(
    contrast: np.ndarray, jacobian: np.ndarray, varpar_cov: np.ndarray, variance: float
) -> float:
    """Satterthwaite df of one contrast ``l``: ``2 (l'Cl)² / (g'Ag)``, ``g_j = l' ∂C/∂varpar_j l``
    (``jacobian`` stacks the ``∂C/∂varpar_j``, ``A`` is ``varpar_cov``)."""
    g = np.einsum("a,jab,b->j", contrast, jacobian, contrast)
    denominator = float(g @ varpar_cov @ g)
    if not np.isfinite(denominator) or denominator <= 0:
        return float("nan")
    return 2.0 * variance**2 / denominator


def f_test_df(
    matrix: np.ndarray,
    beta: np.ndarray,
    cov: np.ndarray,
    jacobian: np.ndarray,
    varpar_cov: np.ndarray,
) -> tuple[float, float, float]:
    """F statistic, numerator and denominator df of ``L β = 0`` (Fai–Cornelius via lmerTest).

    The df depend on the basis of the rows of ``L`` (F does not): pass lmerTest's to get its df.

    The contrasts are rotated to the eigenvectors of ``L C L'`` so they are independent; each gets
    its own Satterthwaite df ``ν_m``; with ``E = Σ ν_m / (ν_m − 2)`` the
    denominator df is ``2E / (E − q)``: equal ``ν_m`` give their common value and any
    ``ν_m ≤ 2`` gives 2, as in lmerTest's ``get_Fstat_ddf``.
    """
    lcl = matrix @ cov @ matrix.T
    values, vectors = np.linalg.eigh(lcl)
    keep = values > 1e-10 * max(values.max(), 1e-300)
    values, vectors = values[keep], vectors[:, keep]
    rotated = vectors.T @ matrix
    q = len(values)
    f = float(np.sum((rotated @ beta) ** 2 / values) / q)
    nus = np.array(
        [contrast_df(row, jacobian, varpar_cov, v) for row, v in zip(rotated, values, strict=True)]
    )
    if q == 1:
        return f, 1.0, float(nus[0])
    if np.any(~np.isfinite(nus)):
        return f, float(q), float("nan")
    if np.all(np.abs(np.diff(nus)) < 1e-8):
        return f, float(q), float(nus.mean())
    if np.any(nus <= 2):
        return f, float(q), 2.0
    e = float(np.sum(nus / (nus - 2)))
    return f, float(q), 2 * e / (e - q)
