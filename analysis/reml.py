"""The REML likelihood of a linear mixed model in lme4's parameterisation, and its optimum.

lme4 writes the random-effects covariance as ``G = σ² Λ Λ'`` with ``Λ`` the lower-triangular
*relative Cholesky factor*, the diagonal of ``Λ`` bounded below by zero. The likelihood is smooth
in ``Λ`` up to and across the boundary of the parameter space (a variance of zero, an
intercept–slope correlation of ±1), where the covariance elements themselves stop being a
valid parameterisation (the likelihood is not even defined beyond it).

:class:`RemlDesign` evaluates the REML deviance in that parameterisation (profiled over ``σ``,
or at a given ``σ``), with exact gradients. The same parameterisation, ``varpar = (θ, σ)``, is
the one lmerTest uses for Satterthwaite's df (:mod:`analysis.satterthwaite`), which therefore
stay valid at the boundary.

statsmodels' ``MixedLM`` finds a good neighbourhood but, on the flat likelihoods of small
samples, sometimes stops short of the optimum, most of all when the optimum is on the boundary,
which its parameterisation can approach but never reach (a correlation of .9958 where lme4
finds 1). :meth:`RemlDesign.refine` therefore finishes every fit here: it minimises the
deviance in ``θ`` and also fits the boundary model (a rank-deficient ``Λ``), keeping it when its
likelihood is at least as good, so a fit whose optimum is on the boundary is reported there.

``θ`` holds the elements of the lower triangle of ``Λ`` column by column (lme4's order:
``Λ[0,0], Λ[1,0], Λ[1,1]`` for an intercept and a slope). The fit is singular, as lme4's
``isSingular``, when a diagonal element of ``Λ`` is below 10⁻⁴.

References
----------
Bates, Mächler, Bolker & Walker (2015). Fitting linear mixed-effects models using lme4. Journal
of Statistical Software 67(1), section 3.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import optimize

__all__ = ["SINGULAR_TOL", "RemlDesign", "RemlFit"]

SINGULAR_TOL = 1e-4
"""A diagonal element of ``Λ`` below this is on the boundary (lme4's ``isSingular`` default)."""

_KEEP_BOUNDARY = 1e-9
"""The boundary fit is kept when its REML deviance is at most this much above the free fit's:
"at least as good" up to the rounding of the deviance itself."""


@dataclass(frozen=True)
class _Block:
    """The groups of one size ``k``: arrays of shape (m, k, ·)."""

    y: np.ndarray
    x: np.ndarray
    z: np.ndarray


@dataclass(frozen=True)
class _Pieces:
    """What every derivative needs at one ``θ`` (all relative to ``σ²``).

    ``m`` is ``(X'V_r⁻¹X)⁻¹``, ``s`` is ``Σ Z'V_r⁻¹Z``, ``t`` is ``Σ B M B'`` and ``u`` is
    ``Σ (Z'V_r⁻¹r)(Z'V_r⁻¹r)'`` with ``B = Z'V_r⁻¹X`` per group; ``b`` stacks the ``B``.
    """

    logdet_v: float
    logdet_xtvx: float
    quad: float
    beta: np.ndarray
    m: np.ndarray
    s: np.ndarray
    t: np.ndarray
    u: np.ndarray
    b: list[np.ndarray]


@dataclass(frozen=True)
class RemlFit:
    """A REML estimate: ``θ`` (relative Cholesky factor), ``σ``, ``β``, ``G`` and the
    log-likelihood, and whether ``θ`` is on the boundary."""

    theta: np.ndarray
    sigma: float
    beta: np.ndarray
    cov_re: np.ndarray
    loglik: float
    singular: bool

    @property
    def varpar(self) -> np.ndarray:
        """``(θ, σ)``: lmerTest's variance parameters."""
        return np.append(self.theta, self.sigma)


class RemlDesign:
    """A mixed model's data grouped by participant, with the REML deviance as a function of θ.

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
    Groups of equal size are stacked, so every evaluation is a handful of batched numpy
    operations however many participants there are.
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
        self.index = [(r, c) for c in range(self.q) for r in range(c, self.q)]
        """(row, column) of each θ element in Λ, lme4's column-major order."""
        self.diagonal = np.array([r == c for r, c in self.index])

    @property
    def n_theta(self) -> int:
        """Number of elements of θ (the lower triangle of Λ)."""
        return len(self.index)

    def factor(self, theta: np.ndarray) -> np.ndarray:
        """``Λ``: the lower-triangular relative Cholesky factor with elements ``θ``."""
        lam = np.zeros((self.q, self.q))
        for (r, c), value in zip(self.index, theta, strict=True):
            lam[r, c] = value
        return lam

    def theta_of(self, cov_re: np.ndarray, scale: float) -> np.ndarray:
        """``θ`` of a random-effects covariance ``G`` and residual variance: the Cholesky factor
        of ``G / σ²``, with a zero column where ``G`` is singular (a boundary fit)."""
        relative = np.atleast_2d(np.asarray(cov_re, dtype=float)) / scale
        lam = np.zeros((self.q, self.q))
        for c in range(self.q):
            pivot = relative[c, c] - lam[c, :c] @ lam[c, :c]
            if pivot <= 1e-12 * max(1.0, np.trace(relative)):
                continue
            lam[c, c] = np.sqrt(pivot)
            for r in range(c + 1, self.q):
                lam[r, c] = (relative[r, c] - lam[r, :c] @ lam[c, :c]) / lam[c, c]
        return np.array([lam[r, c] for r, c in self.index])

    def _pieces(self, theta: np.ndarray) -> _Pieces:
        lam = self.factor(theta)
        relative_g = lam @ lam.T
        xtvx = np.zeros((self.p, self.p))
        xtvy = np.zeros(self.p)
        logdet_v = 0.0
        inverses = []
        for block in self.blocks:
            v = block.z @ relative_g @ np.swapaxes(block.z, 1, 2) + np.eye(block.z.shape[1])
            logdet_v += float(np.linalg.slogdet(v)[1].sum())
            w = np.linalg.inv(v)
            inverses.append(w)
            wx = w @ block.x
            xtvx += np.einsum("mki,mkj->ij", block.x, wx)
            xtvy += np.einsum("mki,mk->i", wx, block.y)
        m = np.linalg.inv(xtvx)
        beta = m @ xtvy
        quad = 0.0
        s = np.zeros((self.q, self.q))
        t = np.zeros((self.q, self.q))
        u = np.zeros((self.q, self.q))
        bs = []
        for block, w in zip(self.blocks, inverses, strict=True):
            r = block.y - block.x @ beta
            wr = np.einsum("mkl,ml->mk", w, r)
            quad += float(np.einsum("mk,mk->", r, wr))
            zt = np.swapaxes(block.z, 1, 2)
            b = zt @ w @ block.x  # (m, q, p)
            zwr = np.einsum("mqk,mk->mq", zt, wr)
            s += np.einsum("mqk,mkl,mlr->qr", zt, w, block.z)
            t += np.einsum("mqp,pd,mrd->qr", b, m, b)
            u += np.einsum("mq,mr->qr", zwr, zwr)
            bs.append(b)
        return _Pieces(
            logdet_v=logdet_v,
            logdet_xtvx=float(np.linalg.slogdet(xtvx)[1]),
            quad=quad,
            beta=beta,
            m=m,
            s=s,
            t=t,
            u=u,
            b=bs,
        )

    def _theta_gradient(self, pieces: _Pieces, theta: np.ndarray, k: np.ndarray) -> np.ndarray:
        """``∂/∂θ_j`` of a deviance whose derivative in ``G_r = ΛΛ'`` is the symmetric ``k``:
        ``tr((E_jΛ' + ΛE_j') k) = 2 (kΛ)[row_j, col_j]``."""
        kl = k @ self.factor(theta)
        return np.array([2 * kl[r, c] for r, c in self.index])

    def profiled_deviance(self, theta: np.ndarray) -> tuple[float, np.ndarray]:
        """The REML deviance (−2 log-likelihood) at ``θ`` with ``σ²`` at its optimum
        ``Q / (n − p)``, and its gradient in ``θ`` (lme4's REML criterion)."""
        pieces = self._pieces(theta)
        dof = self.n - self.p
        quad = max(pieces.quad, 1e-300)
        deviance = pieces.logdet_v + pieces.logdet_xtvx + dof * (1 + np.log(2 * np.pi * quad / dof))
        k = pieces.s - pieces.t - dof / quad * pieces.u
        return float(deviance), self._theta_gradient(pieces, theta, k)

    def deviance(self, varpar: np.ndarray) -> float:
        """The REML deviance at ``varpar = (θ, σ)`` (σ not profiled: lmerTest's ``devfun_vp``)."""
        return self.deviance_and_gradient(varpar)[0]

    def deviance_and_gradient(self, varpar: np.ndarray) -> tuple[float, np.ndarray]:
        """The REML deviance at ``(θ, σ)`` and its gradient in ``(θ, σ)``."""
        theta, sigma = np.asarray(varpar[:-1], float), float(varpar[-1])
        pieces = self._pieces(theta)
        dof = self.n - self.p
        sigma2 = sigma**2
        deviance = (
            pieces.logdet_v
            + pieces.logdet_xtvx
            + pieces.quad / sigma2
            + dof * np.log(2 * np.pi * sigma2)
        )
        k = pieces.s - pieces.t - pieces.u / sigma2
        gradient = np.append(
            self._theta_gradient(pieces, theta, k), 2 * dof / sigma - 2 * pieces.quad / sigma**3
        )
        return float(deviance), gradient

    def beta_covariance_jacobian(self, varpar: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``Var(β̂) = σ² (X'V_r⁻¹X)⁻¹`` at ``(θ, σ)`` and its exact derivatives in each element
        of ``(θ, σ)``, shape (n_theta + 1, p, p) (lmerTest's ``Jac_list``)."""
        theta, sigma = np.asarray(varpar[:-1], float), float(varpar[-1])
        pieces = self._pieces(theta)
        lam = self.factor(theta)
        jacobian = np.zeros((self.n_theta + 1, self.p, self.p))
        for j, (r, c) in enumerate(self.index):
            unit = np.zeros((self.q, self.q))
            unit[r, c] = 1.0
            d_g = unit @ lam.T + lam @ unit.T  # ∂(ΛΛ')/∂θ_j
            # ∂(X'V_r⁻¹X)/∂θ_j = −Σ B' ∂G B, so ∂M/∂θ_j = M (Σ B' ∂G B) M
            inner = sum(np.einsum("mqp,qr,mrs->ps", b, d_g, b) for b in pieces.b)
            jacobian[j] = sigma**2 * pieces.m @ inner @ pieces.m
        jacobian[-1] = 2 * sigma * pieces.m
        return sigma**2 * pieces.m, jacobian

    def estimates(self, theta: np.ndarray) -> RemlFit:
        """β, σ, G and the REML log-likelihood at ``θ`` (σ² at its optimum)."""
        theta = self._canonical(np.asarray(theta, float))
        pieces = self._pieces(theta)
        deviance, _ = self.profiled_deviance(theta)
        sigma2 = pieces.quad / (self.n - self.p)
        lam = self.factor(theta)
        return RemlFit(
            theta=theta,
            sigma=float(np.sqrt(sigma2)),
            beta=pieces.beta,
            cov_re=sigma2 * lam @ lam.T,
            loglik=-0.5 * deviance,
            singular=bool(np.any(theta[self.diagonal] < SINGULAR_TOL)),
        )

    def refine(self, start: np.ndarray) -> RemlFit:
        """The REML optimum, from ``start`` (a θ), checked against the boundary.

        The profiled deviance is minimised over θ without bounds (it depends on Λ only through
        ΛΛ', which flipping the sign of a column of Λ leaves unchanged, so nothing is lost; and
        no bound can stall the search at the boundary, where the gradient is zero), from
        ``start`` and from lme4's default start (Λ = I), which guards against a start in the
        wrong valley or on the stationary point θ = 0. Then the boundary model (the last
        diagonal element of Λ fixed at zero: a variance of zero with one random effect; a
        rank-one covariance, i.e. a correlation of ±1 or a zero variance, with two) is fitted
        and kept when its likelihood is at least as good, so a fit that only approaches the
        boundary is reported on it, as lme4's bounded optimiser ends on it.
        """
        free_starts = [np.asarray(start, float), self._default_start()]
        free = min((self._minimise(s, fixed=None) for s in free_starts), key=lambda r: r.fun)
        last = int(np.flatnonzero(self.diagonal)[-1])
        boundary = self._minimise(free.x, fixed=last)
        best = boundary if boundary.fun <= free.fun + _KEEP_BOUNDARY else free
        return self.estimates(best.x)

    def _default_start(self) -> np.ndarray:
        return self.diagonal.astype(float)

    def _canonical(self, theta: np.ndarray) -> np.ndarray:
        """The same ΛΛ' with a non-negative diagonal: flip the sign of each column of Λ whose
        diagonal element is negative (lme4's convention)."""
        lam = self.factor(theta)
        lam = lam * np.where(np.diag(lam) < 0, -1.0, 1.0)[None, :]
        return np.array([lam[r, c] for r, c in self.index])

    def _minimise(self, start: np.ndarray, fixed: int | None) -> optimize.OptimizeResult:
        """BFGS on the profiled deviance, with θ[fixed] held at zero when given."""
        free = np.ones(self.n_theta, dtype=bool)
        if fixed is not None:
            free[fixed] = False

        def deviance(values: np.ndarray) -> tuple[float, np.ndarray]:
            theta = np.zeros(self.n_theta)
            theta[free] = values
            value, gradient = self.profiled_deviance(theta)
            return value, gradient[free]

        if not free.any():  # a single random effect at zero: nothing to optimise
            value, _ = self.profiled_deviance(np.zeros(self.n_theta))
            return optimize.OptimizeResult(x=np.zeros(self.n_theta), fun=value)
        result = optimize.minimize(
            deviance, start[free], jac=True, method="BFGS", options={"gtol": 1e-9, "maxiter": 500}
        )
        theta = np.zeros(self.n_theta)
        theta[free] = result.x
        return optimize.OptimizeResult(x=theta, fun=float(result.fun))
