"""Standard errors of a least-squares fit to logs whose residual is correlated in time.

The textbook covariance of a least-squares fit, ``s^2 (J^T J)^-1`` (``J`` the residual's Jacobian at the optimum,
``s^2`` the residual's variance per degree of freedom), holds where the residual's samples are independent: a model
that is the robot, and sensors whose noise is white.  A replay that differs from the robot (a machine stepped finer
than the model, a drive that filters what it reports) leaves a residual smooth in time: a hundred samples in a row
err alike, and the data determine the values no better than a few independent samples would.  Against a bridge log
of the simulated robot stepped four times per current-loop tick, replayed at the model's step, 8 of the 28 textbook
95 % intervals covered the truth (``docs/identify.md``).

:func:`covariance` counts that correlation, with the heteroskedasticity- and autocorrelation-consistent covariance
of Newey and West (1987)::

    cov = (J^T J)^-1 Omega (J^T J)^-1 n / (n - p),
    Omega = G_0 + sum_{l=1..L} (1 - l / (L + 1)) (G_l + G_l^T),    G_l = sum_t g_t g_{t-l}^T  (within each log),

``g_t`` the sum of ``J_i r_i`` over the residual's entries ``i`` of sample ``t`` (every axis and channel of one
instant), ``n`` the entries, ``p`` the values.  Bartlett's weights keep ``Omega`` positive semi-definite.  With
``L = 0`` and independent entries it is White's covariance, which the textbook one equals where the residual's
variance is the same everywhere.

*The bandwidth* ``L`` (in samples) is the one of the grid 0, 1, 2, 4, ... up to a quarter of the shortest log that
gives the largest errors (the mean over the values of the logarithm of their variances): the most cautious of the
grid.  The usual automatic bandwidth (Andrews 1991, from each score's first autocorrelation) does not work here: at
the optimum the scores sum to zero (the normal equations), so ``Omega`` falls again as ``L`` nears the log's length,
and a residual whose autocorrelation is 0.999 a sample, as a model error's is, sends that rule there (1310 samples
of the 2000 of the log above, 17 of 28 intervals covering, against 26 at the grid's 128).  On a linear fit to two
logs of 1000 samples with AR(1) noise, over 200 draws (``tests/test_identify.py``), the grid's rule covers 95 % of
the truths with white noise (the textbook intervals as much) and 79-90 % with autocorrelations of 0.9 to 0.995 a
sample, where the textbook intervals cover 13-35 %: Bartlett's weights still undercount a correlation that strong,
but by far less.

*Never below the textbook errors.*  Where the residual's variance differs between the samples that carry a value
and the others (the currents against the angles, fast moves against slow ones), Newey-West's estimate can fall below
the textbook one, and is then the more often too small: on two noise draws of the excitation path's log written by
the replay itself (17-bit encoders, 1 % current noise), the friction values' errors came out at 0.65 to 0.8 of the
textbook ones, and 26 of the 28 intervals covered the truth in each, against 27 and 28 textbook ones.  So each
value's variance is the larger of the two; the correlations stay Newey-West's.
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class Covariance:
    """The fitted values' ``covariance`` ``(p, p)`` (in the values' units squared) and the ``bandwidth`` [samples]
    it took (0: the samples' errors taken as independent)."""

    covariance: np.ndarray
    bandwidth: int


def bandwidths(shortest: int) -> list[int]:
    """The grid of :func:`covariance`'s bandwidths [samples] for logs of at least ``shortest`` samples: 0, then the
    powers of 2 up to a quarter of it."""
    return [0] + [2**k for k in range(max(shortest // 4, 1).bit_length()) if 2**k <= shortest // 4]


def textbook(J: np.ndarray, r: np.ndarray) -> np.ndarray:
    """The textbook covariance ``s^2 (J^T J)^+`` of a least-squares fit's values at its optimum (``J`` ``(n, p)`` the
    residual's Jacobian there, ``r`` ``(n,)`` the residual, ``s^2`` its variance per degree of freedom): each entry's
    error taken as independent of the others."""
    n, p = J.shape
    covariance: np.ndarray = np.linalg.pinv(J.T @ J) * (float(r @ r) / max(n - p, 1))
    return covariance


def covariance(J: np.ndarray, r: np.ndarray, samples: np.ndarray, logs: list[int]) -> Covariance:
    """The Newey-West covariance of the values of a least-squares fit at its optimum, each variance at least the
    textbook one (module docstring): ``J`` ``(n, p)`` the residual's Jacobian there, ``r`` ``(n,)`` the residual,
    ``samples`` ``(n,)`` each entry's sample (from 0, counted across the logs in order), ``logs`` the samples of each
    log, in order."""
    n, p = J.shape
    G = np.zeros((sum(logs), p))
    np.add.at(G, samples, J * r[:, None])
    inverse = np.linalg.pinv(J.T @ J)
    grid = bandwidths(min(logs))
    ends = np.cumsum([0, *logs])
    pieces = [G[a:b] for a, b in zip(ends[:-1], ends[1:])]  # each log's scores
    # G_l for l = 0 .. the grid's largest, each summed over the logs (no lag reaches from one log into the next)
    lags = [np.sum([g[lag:].T @ g[: len(g) - lag] for g in pieces], axis=0) for lag in range(grid[-1] + 1)]
    best: Covariance | None = None
    score = -np.inf
    for L in grid:
        omega = lags[0] + sum((1 - k / (L + 1)) * (lags[k] + lags[k].T) for k in range(1, L + 1))
        cov = inverse @ omega @ inverse * (n / max(n - p, 1))
        variances = np.diag(cov)
        kept = variances > 0
        mean_log = float(np.mean(np.log(variances[kept]))) if kept.any() else -np.inf
        if best is None or mean_log > score:
            best, score = Covariance((cov + cov.T) / 2, L), mean_log
    assert best is not None
    # each value's variance at least the textbook one, s^2 (J^T J)^-1 (the correlations Newey-West's): where the
    # residual's variance differs between the samples that carry a value and the others, White's and Newey-West's
    # estimates fall below it, and over noise draws of a log the replay matches they covered the truth less often
    floor = np.diag(textbook(J, r))
    variances = np.diag(best.covariance)
    safe = np.where(variances > 0, variances, 1.0)
    raise_by = np.where(variances > 0, np.sqrt(np.maximum(floor, variances) / safe), 1.0)
    return Covariance(best.covariance * np.outer(raise_by, raise_by), best.bandwidth)
