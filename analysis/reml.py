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

:meth:`RemlDesign.refine` is the whole fit: it minimises the profiled deviance in ``θ`` from
lme4's start and also fits the boundary model (a rank-deficient ``Λ``), keeping it when its
likelihood is at least as good, so a fit whose optimum is on the boundary is reported there
(statsmodels' ``MixedLM``, used before, could approach the boundary but never reach it: a
correlation of .9958 where lme4 finds 1, and it took seconds where this takes milliseconds).
With one grouping factor the criterion is evaluated from per-group sufficient statistics in
batched numpy (:class:`RemlDesign`'s Notes), which is what makes the fit faster than lme4's.

``θ`` holds the elements of the lower triangle of ``Λ`` column by column (lme4's order:
``Λ[0,0], Λ[1,0], Λ[1,1]`` for an intercept and a slope). The fit is singular, as lme4's
``isSingular``, when a diagonal element of ``Λ`` is below 10⁻⁴.

References
----------
Bates, Mächler, Bolker & Walker (2015). Fitting linear mixed-effects models using lme4. Journal
of Statistical Software 67(1), section 3.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from scipy import optimize

__all__ = ["MAX_ITERATIONS", "SINGULAR_TOL", "RemlDesign", "RemlFit"]

SINGULAR_TOL = 1e-4
"""A diagonal element of ``Λ`` below this is on the boundary (lme4's ``isSingular`` default)."""

MAX_ITERATIONS = 500
"""BFGS iterations allowed per minimisation (a few dozen are used)."""

_KEEP_BOUNDARY = 1e-9
"""The boundary fit is kept when its REML deviance is at most this much above the free fit's:
"at least as good" up to the rounding of the deviance itself."""


@dataclass(frozen=True)
class _Pieces:
    """What the deviance and every derivative need at one ``θ`` (all relative to ``σ²``).

    ``m`` is ``(X'V_r⁻¹X)⁻¹``, ``s`` is ``Σ Z'V_r⁻¹Z``, ``t`` is ``Σ B M B'`` and ``u`` is
    ``Σ (Z'V_r⁻¹r)(Z'V_r⁻¹r)'`` with ``B = Z'V_r⁻¹X`` per group; ``b`` stacks the ``B`` of
    each design pattern, shape (P, q, p) (:class:`RemlDesign`'s ``counts`` say how many groups
    share each).
    """

    logdet_v: float
    logdet_xtvx: float
    quad: float
    beta: np.ndarray
    m: np.ndarray
    s: np.ndarray
    t: np.ndarray
    u: np.ndarray
    b: np.ndarray


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
    iterations: int = 0
    """BFGS iterations of the minimisation whose optimum was kept."""
    max_gradient: float = 0.0
    """Largest ``|∂ deviance / ∂θ_j|`` at ``θ`` (the profiled REML criterion): how far from
    stationary the optimiser stopped (lme4 warns above 0.002)."""

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
    With one grouping factor, ``V_r = I + Z Λ Λ' Z'`` is block diagonal and, by Woodbury,
    ``V_r⁻¹ = I − Z Λ A⁻¹ Λ' Z'`` with ``A = Λ'Z'ZΛ + I`` one ``q × q`` block per group (lme4's
    sparse Cholesky factor of the penalised least-squares system is exactly this batch of blocks)
    and ``log|V_r| = log|A|``. So every quantity of the criterion and its derivatives is a
    function of the per-group sufficient statistics ``Z_i'Z_i``, ``Z_i'X_i``, ``Z_i'y_i`` and of
    ``X'X``, ``X'y``, ``y'y``, computed once here: an evaluation is a few batched ``q × q``
    operations over the groups (``q`` is 1 or 2), whatever the number of ratings per group, with
    no Python loop over participants and no ``n × n`` matrix.
    """

    def __init__(self, y: np.ndarray, x: np.ndarray, z: np.ndarray, groups: np.ndarray) -> None:
        order = np.argsort(np.asarray(groups), kind="stable")
        codes = np.asarray(groups)[order]
        y = np.asarray(y, dtype=float)[order]
        x = np.asarray(x, dtype=float)[order]
        z = np.asarray(z, dtype=float)[order]
        starts = np.flatnonzero(np.concatenate([[True], codes[1:] != codes[:-1]]))
        self.n, self.p = x.shape
        self.q = z.shape[1]
        self.n_groups = len(starts)
        ztz = np.add.reduceat(z[:, :, None] * z[:, None, :], starts, axis=0)
        ztx = np.add.reduceat(z[:, :, None] * x[:, None, :], starts, axis=0)
        zty = np.add.reduceat(z * y[:, None], starts, axis=0)
        # Groups with the same design (same condition, same sessions rated) share Z_i'Z_i and
        # Z_i'X_i, so A_i, its inverse and B_i too: only y differs, and y enters the criterion
        # through Σ Z_i'y_i and Σ (Z_i'y_i)(Z_i'y_i)' over the groups of one pattern. A 2 × 4
        # study has at most 2 × 15 patterns, so an evaluation costs the same for 24 or 10,000
        # participants; a continuous covariate makes every group its own pattern (no loss).
        key = np.concatenate([ztz.reshape(len(starts), -1), ztx.reshape(len(starts), -1)], 1)
        # Each row's bytes as one value: np.unique(axis=0) compares field by field, 10× slower.
        rows = np.ascontiguousarray(key).view(np.dtype((np.void, key.itemsize * key.shape[1])))
        _, first, inverse, counts = np.unique(
            rows.ravel(), return_index=True, return_inverse=True, return_counts=True
        )
        patterns = key[first]
        inverse = inverse.reshape(-1)
        self.counts = counts.astype(float)
        """Groups per design pattern, shape (P,)."""
        self.ztz = patterns[:, : self.q**2].reshape(-1, self.q, self.q)
        """``Z_i'Z_i`` of each pattern, shape (P, q, q)."""
        self.ztx = patterns[:, self.q**2 :].reshape(-1, self.q, self.p)
        """``Z_i'X_i`` of each pattern, shape (P, q, p)."""
        self.zty = np.zeros((len(patterns), self.q))
        np.add.at(self.zty, inverse, zty)
        """``Σ Z_i'y_i`` over each pattern's groups, shape (P, q)."""
        self.zty_outer = np.zeros((len(patterns), self.q, self.q))
        np.add.at(self.zty_outer, inverse, zty[:, :, None] * zty[:, None, :])
        """``Σ (Z_i'y_i)(Z_i'y_i)'`` over each pattern's groups, shape (P, q, q)."""
        self.xtx = x.T @ x
        self.xty = x.T @ y
        self.yty = float(y @ y)
        self.y_sum = float(y.sum())
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

    def residual_share(self) -> float:
        """The share of ``y``'s total sum of squares that neither the fixed effects nor any
        group's own random effects reproduce: ``y`` is projected off each group's random-effect
        columns (Frisch–Waugh, from the sufficient statistics) and then regressed on the
        projected fixed effects. Zero (to rounding) means no residual variation: REML then has
        no optimum."""
        projector = np.linalg.pinv(self.ztz)  # (Z_i'Z_i)⁺ of each pattern
        xx = self.xtx - np.einsum("P,Pqp,Pqr,Prs->ps", self.counts, self.ztx, projector, self.ztx)
        xy = self.xty - np.einsum("Pqp,Pqr,Pr->p", self.ztx, projector, self.zty)
        yy = self.yty - float(np.einsum("Pqr,Prq->", projector, self.zty_outer))
        coef = np.linalg.lstsq(xx, xy, rcond=1e-10)[0]
        total = self.yty - self.y_sum**2 / self.n
        return max(yy - float(xy @ coef), 0.0) / total if total > 0 else 0.0

    def _pieces(self, theta: np.ndarray) -> _Pieces:
        lam = self.factor(theta)
        c = self.counts
        # A_i = Λ'Z_i'Z_iΛ + I and W_i = Λ A_i⁻¹ Λ', so that V_i⁻¹ = I − Z_i W_i Z_i'.
        a = lam.T @ self.ztz @ lam + np.eye(self.q)
        logdet_v = float(c @ np.linalg.slogdet(a)[1])
        w = lam @ np.linalg.inv(a) @ lam.T
        # D_i = I − Z_i'Z_i W_i turns Z_i'· into Z_i'V_i⁻¹·: B_i = D_i Z_i'X_i, and so on.
        d = np.eye(self.q) - self.ztz @ w
        b = d @ self.ztx  # Z'V⁻¹X of each pattern, (P, q, p)
        wzx = w @ self.ztx
        wzy = np.einsum("Pqr,Pr->Pq", w, self.zty)
        xtvx = self.xtx - np.einsum("P,Pqp,Pqs->ps", c, self.ztx, wzx)
        xtvy = self.xty - np.einsum("Pqp,Pq->p", self.ztx, wzy)
        ytvy = self.yty - float(np.einsum("Pqr,Prq->", w, self.zty_outer))
        m = np.linalg.inv(xtvx)
        beta = m @ xtvy
        quad = ytvy - float(beta @ xtvy)
        s = np.einsum("P,Pqr,Prs->qs", c, d, self.ztz)
        bm = b @ m
        t = np.einsum("P,Pqp,Prp->qr", c, bm, b)
        # u = Σ_i (D Z_i'y_i − B β)(D Z_i'y_i − B β)' summed within each pattern.
        dzy = np.einsum("Pqr,Pr->Pq", d, self.zty)
        bb = b @ beta
        cross = np.einsum("Pq,Pr->qr", dzy, bb)
        u = (
            np.einsum("Pqr,Prs,Pts->qt", d, self.zty_outer, d)
            - cross
            - cross.T
            + np.einsum("P,Pq,Pr->qr", c, bb, bb)
        )
        return _Pieces(
            logdet_v=logdet_v,
            logdet_xtvx=float(np.linalg.slogdet(xtvx)[1]),
            quad=quad,
            beta=beta,
            m=m,
            s=s,
            t=t,
            u=u,
            b=b,
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
            inner = np.einsum("P,Pqp,qr,Prs->ps", self.counts, pieces.b, d_g, pieces.b)
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

    def refine(
        self, start: np.ndarray | None = None, *, max_iterations: int = MAX_ITERATIONS
    ) -> RemlFit:
        """The REML optimum, from lme4's start (Λ = I) and ``start`` (a θ) if given, checked
        against the boundary.

        The profiled deviance is minimised over θ without bounds (it depends on Λ only through
        ΛΛ', which flipping the sign of a column of Λ leaves unchanged, so the bound lme4 puts on
        the diagonal loses nothing; and no bound can stall the search at the boundary, where the
        gradient is zero). Then the boundary model (the last diagonal element of Λ fixed at
        zero: a variance of zero with one random effect; a rank-one covariance, i.e. a
        correlation of ±1 or a zero variance, with two) is fitted and kept when its likelihood is
        at least as good, so a fit that only approaches the boundary is reported on it, as
        lme4's bounded optimiser ends on it. ``max_iterations`` bounds each BFGS run; the
        result's ``max_gradient`` says whether it stopped at a stationary point.
        """
        starts = [self._default_start()]
        if start is not None and not np.allclose(start, starts[0]):
            starts.append(np.asarray(start, float))
        free = min((self._minimise(s, None, max_iterations) for s in starts), key=lambda r: r.fun)
        last = int(np.flatnonzero(self.diagonal)[-1])
        boundary = self._minimise(free.x, last, max_iterations)
        best = boundary if boundary.fun <= free.fun + _KEEP_BOUNDARY else free
        fit = self.estimates(best.x)
        _, gradient = self.profiled_deviance(fit.theta)
        return replace(fit, iterations=int(best.nit), max_gradient=float(np.max(np.abs(gradient))))

    def _default_start(self) -> np.ndarray:
        return self.diagonal.astype(float)

    def _canonical(self, theta: np.ndarray) -> np.ndarray:
        """The same ΛΛ' with a non-negative diagonal: flip the sign of each column of Λ whose
        diagonal element is negative (lme4's convention)."""
        lam = self.factor(theta)
        lam = lam * np.where(np.diag(lam) < 0, -1.0, 1.0)[None, :]
        return np.array([lam[r, c] for r, c in self.index])

    def _minimise(
        self, start: np.ndarray, fixed: int | None, max_iterations: int
    ) -> optimize.OptimizeResult:
        """BFGS on the profiled deviance, with θ[fixed] held at zero when given, then Newton.

        BFGS is stopped at a gradient of 10⁻⁶ and Newton's method on the exact gradient (its
        Jacobian by central differences) finishes: two Newton steps reach the optimum to the
        precision of the gradient itself, where BFGS needed three to five times the evaluations
        to crawl the last digits (its line search is limited by the rounding of the deviance).
        """
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
            return optimize.OptimizeResult(x=np.zeros(self.n_theta), fun=value, nit=0)
        result = optimize.minimize(
            deviance,
            start[free],
            jac=True,
            method="BFGS",
            options={"gtol": 1e-6, "maxiter": max_iterations},
        )
        values, value = _newton(deviance, result.x, float(result.fun))
        theta = np.zeros(self.n_theta)
        theta[free] = values
        return optimize.OptimizeResult(x=theta, fun=value, nit=int(result.nit))


def _newton(
    deviance: Callable[[np.ndarray], tuple[float, np.ndarray]],
    x: np.ndarray,
    value: float,
    steps: int = 3,
) -> tuple[np.ndarray, float]:
    """Up to ``steps`` Newton steps on the gradient of ``deviance`` from ``x``, each kept only
    when it lowers the gradient without raising the deviance (beyond its rounding); a Hessian
    that is not positive definite (a flat direction, e.g. towards the boundary) stops them."""
    _, gradient = deviance(x)
    for _ in range(steps):
        size = float(np.max(np.abs(gradient)))
        if size < 1e-11:
            break
        hessian = np.zeros((len(x), len(x)))
        for i in range(len(x)):
            step = np.zeros(len(x))
            step[i] = 1e-5 * max(abs(x[i]), 1e-2)
            hessian[i] = (deviance(x + step)[1] - deviance(x - step)[1]) / (2 * step[i])
        try:
            factor = np.linalg.cholesky((hessian + hessian.T) / 2)
        except np.linalg.LinAlgError:
            break
        move = np.linalg.solve(factor.T, np.linalg.solve(factor, gradient))
        new_value, new_gradient = deviance(x - move)
        if not (
            np.max(np.abs(new_gradient)) < size and new_value <= value + 1e-10 * max(1, abs(value))
        ):
            break
        x, value, gradient = x - move, new_value, new_gradient
    return x, value
