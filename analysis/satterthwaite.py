"""Satterthwaite degrees of freedom for the fixed effects of a linear mixed model.

statsmodels' MixedLM fits the model (REML) but tests fixed effects with z statistics, which are
too liberal with the 20–60 participants of an HRI study. lmerTest, SAS and JASP use
Satterthwaite's approximation instead; this module computes it for a fitted model, so a PI gets
the same t and F tests as R's ``lmerTest``.

For a contrast ``l``, the variance of ``l'β̂`` is ``v(θ) = l' C(θ) l`` with
``C(θ) = (X' V(θ)⁻¹ X)⁻¹``, where ``θ`` holds the random-effect covariances and the residual
variance. Satterthwaite's df is ``2 v² / (g' A g)`` with ``g = ∂v/∂θ`` (exact, below) and ``A`` the
asymptotic covariance of ``θ̂``: the inverse of the negative Hessian of the REML log-likelihood
at the estimate (by central differences, as lmerTest does). F tests of several contrasts combine
the single-contrast dfs as Fai & Cornelius (1996) and lmerTest's ``contestMD`` do.

Nothing here optimises: the estimates come from statsmodels; this module only evaluates the REML
likelihood and its derivatives at them. The df is invariant to how ``θ`` is parameterised, so the
covariance elements are used directly.

References
----------
Kuznetsova, Brockhoff & Christensen (2017). lmerTest package: tests in linear mixed effects
models. Journal of Statistical Software 82(13).
Fai & Cornelius (1996). Approximate F-tests of multiple degree of freedom hypotheses in
generalized least squares analyses of unbalanced split-plot experiments. J. Stat. Comput. Simul.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["RemlDesign", "contrast_df", "f_test_df"]


@dataclass(frozen=True)
class _Block:
    """The groups of one size ``k``: arrays of shape (m, k, ·)."""

    y: np.ndarray
    x: np.ndarray
    z: np.ndarray


class RemlDesign:
    """A mixed model's data grouped by participant, with the REML quantities as functions of θ.

    Parameters
    ----------
    y : numpy.ndarray
        Responses, shape (n,).
    x : numpy.ndarray
        Fixed-effects design, shape (n, p).
    z : numpy.ndarray
        Random-effects design, shape (n, q) (a column of ones for a random intercept).
    groups : numpy.ndarray
        Group code of each row, shape (n,).

    Notes
    -----
    ``θ`` is ``(G[0,0], G[1,0], G[1,1], …, σ²)``: the lower triangle of the random-effects
    covariance ``G`` row by row, then the residual variance. Groups of equal size are stacked,
    so every evaluation is a handful of batched numpy operations however many participants
    there are.
    """

    def __init__(self, y: np.ndarray, x: np.ndarray, z: np.ndarray, groups: np.ndarray) -> None:
        y = np.asarray(y, dtype=float)
        x = np.asarray(x, dtype=float)
        z = np.asarray(z, dtype=float)
        order = np.argsort(groups, kind="stable")
        codes = np.asarray(groups)[order]
        starts = np.flatnonzero(np.concatenate([[True], codes[1:] != codes[:-1]]))
        sizes = np.diff(np.concatenate([starts, [len(codes)]]))
        self.n, self.p = x.shape
        self.q = z.shape[1]
        self.blocks: list[_Block] = []
        for k in np.unique(sizes):
            first = starts[sizes == k]
            rows = order[(first[:, None] + np.arange(k)[None, :])]
            self.blocks.append(_Block(y=y[rows], x=x[rows], z=z[rows]))
        self._pairs = [(a, b) for a in range(self.q) for b in range(a + 1)]

    @property
    def n_theta(self) -> int:
        """Number of covariance parameters: the lower triangle of G plus the residual variance."""
        return len(self._pairs) + 1

    def theta(self, cov_re: np.ndarray, scale: float) -> np.ndarray:
        """``θ`` from a random-effects covariance matrix and a residual variance."""
        return np.array([cov_re[a, b] for a, b in self._pairs] + [scale], dtype=float)

    def _g(self, theta: np.ndarray) -> np.ndarray:
        g = np.zeros((self.q, self.q))
        for (a, b), value in zip(self._pairs, theta[:-1], strict=True):
            g[a, b] = g[b, a] = value
        return g

    def _v_inverse(self, block: _Block, theta: np.ndarray) -> np.ndarray:
        v = block.z @ self._g(theta) @ np.swapaxes(block.z, 1, 2)
        v = v + theta[-1] * np.eye(block.z.shape[1])
        return np.linalg.inv(v)

    def reml_loglik(self, theta: np.ndarray) -> float:
        """The REML log-likelihood at ``θ`` (−∞ where V is not positive definite)."""
        xtvx = np.zeros((self.p, self.p))
        xtvy = np.zeros(self.p)
        logdet_v = 0.0
        inverses = []
        for block in self.blocks:
            v = block.z @ self._g(theta) @ np.swapaxes(block.z, 1, 2)
            v = v + theta[-1] * np.eye(block.z.shape[1])
            sign, logdet = np.linalg.slogdet(v)
            if np.any(sign <= 0):
                return -np.inf
            logdet_v += float(logdet.sum())
            w = np.linalg.inv(v)
            inverses.append(w)
            wx = w @ block.x
            xtvx += np.einsum("mki,mkj->ij", block.x, wx)
            xtvy += np.einsum("mki,mk->i", wx, block.y)
        sign, logdet_xtvx = np.linalg.slogdet(xtvx)
        if sign <= 0:
            return -np.inf
        beta = np.linalg.solve(xtvx, xtvy)
        quad = 0.0
        for block, w in zip(self.blocks, inverses, strict=True):
            r = block.y - block.x @ beta
            quad += float(np.einsum("mk,mkl,ml->", r, w, r))
        return -0.5 * (logdet_v + logdet_xtvx + quad + (self.n - self.p) * np.log(2 * np.pi))

    def covariance_and_gradient(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``C(θ) = (X'V⁻¹X)⁻¹`` and its derivatives ``∂C/∂θ_j`` (shape (n_theta, p, p))."""
        xtvx = np.zeros((self.p, self.p))
        pieces = np.zeros((self.n_theta, self.p, self.p))
        for block in self.blocks:
            w = self._v_inverse(block, theta)
            wx = w @ block.x  # (m, k, p)
            xtvx += np.einsum("mki,mkj->ij", block.x, wx)
            zwx = np.swapaxes(block.z, 1, 2) @ wx  # (m, q, p)
            for j, (a, b) in enumerate(self._pairs):
                # V_j = Z E_ab Z'  →  X'W V_j W X = (Z'WX)_a' (Z'WX)_b (+ the mirror when a ≠ b)
                term = np.einsum("mi,mj->ij", zwx[:, a, :], zwx[:, b, :])
                pieces[j] += term if a == b else term + term.T
            pieces[-1] += np.einsum("mki,mkj->ij", wx, wx)
        c = np.linalg.inv(xtvx)
        return c, np.einsum("ab,jbc,cd->jad", c, pieces, c)

    def theta_covariance(self, theta: np.ndarray) -> np.ndarray:
        """Asymptotic covariance of ``θ̂``: the inverse negative Hessian of the REML
        log-likelihood, by central differences with steps relative to each parameter."""
        with np.errstate(all="ignore"):  # steps past a boundary give -inf, checked below
            hess = self._hessian(theta)
        if not np.all(np.isfinite(hess)):
            raise np.linalg.LinAlgError("the REML likelihood is not finite around the estimate")
        return np.linalg.inv(-hess)

    def _hessian(self, theta: np.ndarray) -> np.ndarray:
        h = 1e-4 * np.maximum(np.abs(theta), 1e-3 * max(abs(theta[-1]), 1e-12))
        k = len(theta)
        hess = np.zeros((k, k))
        f0 = self.reml_loglik(theta)
        for i in range(k):
            ei = np.zeros(k)
            ei[i] = h[i]
            hess[i, i] = (self.reml_loglik(theta + ei) - 2 * f0 + self.reml_loglik(theta - ei)) / h[
                i
            ] ** 2
            for j in range(i):
                ej = np.zeros(k)
                ej[j] = h[j]
                hess[i, j] = hess[j, i] = (
                    self.reml_loglik(theta + ei + ej)
                    - self.reml_loglik(theta + ei - ej)
                    - self.reml_loglik(theta - ei + ej)
                    + self.reml_loglik(theta - ei - ej)
                ) / (4 * h[i] * h[j])
        return hess


def contrast_df(
    contrast: np.ndarray, gradient: np.ndarray, theta_cov: np.ndarray, variance: float
) -> float:
    """Satterthwaite df of one contrast ``l``: ``2 (l'Cl)² / (g'Ag)``, ``g_j = l' ∂C/∂θ_j l``."""
    g = np.einsum("a,jab,b->j", contrast, gradient, contrast)
    denominator = float(g @ theta_cov @ g)
    if not np.isfinite(denominator) or denominator <= 0:
        return float("nan")
    return 2.0 * variance**2 / denominator


def f_test_df(
    matrix: np.ndarray,
    beta: np.ndarray,
    cov: np.ndarray,
    gradient: np.ndarray,
    theta_cov: np.ndarray,
) -> tuple[float, float, float]:
    """F statistic, numerator and denominator df of ``L β = 0`` (Fai–Cornelius via lmerTest).

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
        [contrast_df(row, gradient, theta_cov, v) for row, v in zip(rotated, values, strict=True)]
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
