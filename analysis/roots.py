"""A root of a function of one variable inside a bracket, by Brent's method, in pure Python.

:func:`analysis.power.detectable_effect` solves power(f) = target for f. SciPy's
``optimize.brentq`` does it, but importing ``scipy.optimize`` costs ``trustlab power`` more
than the whole command may take (issue 49); this is the same algorithm (Brent 1973, as
SciPy's C ``brentq`` writes it: inverse quadratic interpolation, secant, bisection when
either would step too little or leave the bracket), so the answers and their tolerances are
the ones the command gave before.

References
----------
Brent (1973). Algorithms for minimization without derivatives, ch. 4. Prentice-Hall.
"""

from __future__ import annotations

import math
from collections.abc import Callable

__all__ = ["brent_root"]


def brent_root(
    func: Callable[[float], float],
    low: float,
    high: float,
    *,
    xtol: float = 2e-12,
    rtol: float = 4 * 2.220446049250313e-16,
    max_iterations: int = 100,
) -> float:
    """An x in ``[low, high]`` with ``func(x) = 0`` to within ``xtol + rtol·|x|``.

    Raises
    ------
    ValueError
        When ``func(low)`` and ``func(high)`` have the same sign (no bracket), or no
        convergence within ``max_iterations``.
    """
    x_pre, x_cur = float(low), float(high)
    f_pre, f_cur = func(x_pre), func(x_cur)
    if f_pre == 0:
        return x_pre
    if f_cur == 0:
        return x_cur
    if math.copysign(1, f_pre) == math.copysign(1, f_cur):
        raise ValueError(f"f({low}) and f({high}) have the same sign: no root is bracketed")
    x_blk = f_blk = s_pre = s_cur = 0.0
    for _ in range(max_iterations):
        if f_pre != 0 and f_cur != 0 and math.copysign(1, f_pre) != math.copysign(1, f_cur):
            x_blk, f_blk = x_pre, f_pre
            s_pre = s_cur = x_cur - x_pre
        if abs(f_blk) < abs(f_cur):  # keep the best estimate in x_cur
            x_pre, x_cur, x_blk = x_cur, x_blk, x_cur
            f_pre, f_cur, f_blk = f_cur, f_blk, f_cur
        delta = (xtol + rtol * abs(x_cur)) / 2
        s_bis = (x_blk - x_cur) / 2
        if f_cur == 0 or abs(s_bis) < delta:
            return x_cur
        if abs(s_pre) > delta and abs(f_cur) < abs(f_pre):
            if x_pre == x_blk:  # secant
                s_try = -f_cur * (x_cur - x_pre) / (f_cur - f_pre)
            else:  # inverse quadratic interpolation
                d_pre = (f_pre - f_cur) / (x_pre - x_cur)
                d_blk = (f_blk - f_cur) / (x_blk - x_cur)
                s_try = -f_cur * (f_blk * d_blk - f_pre * d_pre) / (d_blk * d_pre * (f_blk - f_pre))
            if 2 * abs(s_try) < min(abs(s_pre), 3 * abs(s_bis) - delta):
                s_pre, s_cur = s_cur, s_try
            else:
                s_pre = s_cur = s_bis
        else:
            s_pre = s_cur = s_bis
        x_pre, f_pre = x_cur, f_cur
        x_cur += s_cur if abs(s_cur) > delta else math.copysign(delta, s_bis)
        f_cur = func(x_cur)
    raise ValueError(f"no root found in {max_iterations} iterations")
