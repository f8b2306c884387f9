"""How sure: the Laplace (Gauss-Newton) posterior of the estimated constants.

With noise std s per residual component, Phi / s^2 is a negative log-posterior: the
data term 1/(2 s^2) |e|^2 and the controls' Gaussian prior alpha/(2 s^2) |q - q0|^2.
At the optimum its Gauss-Newton Hessian in (q, s = (log E, nu)) is

    H = ([A_q A_s]^T [A_q A_s] + diag(alpha, 0)) / s^2

(functional.Linearisation). The controls are nuisance parameters: the marginal
covariance of s is the inverse of the Schur complement

    S = A_s^T (I - A_q (A_q^T A_q + alpha I)^-1 A_q^T) A_s / s^2,

the Hessian of the profile Phi*(s) / s^2. The noise s comes from the residual,
s^2 = |e|^2 / (m - p_eff), m the informative residual components and p_eff the trace
of the hat matrix (the effective number of fitted parameters), unless ``[target] noise``
gives it. In log E the interval is symmetric; reported in E it is not.

What this interval states is noise only: a model bias -- a mesh too coarse, bases that
cannot represent the wall motion -- is not in it (see the README). Identifiability: a
constant whose 95 % interval is wider than its bounds is not determined by the data.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fenics_elasto.functional import Linearisation


@dataclass
class Posterior:
    labels: list[str]
    s: np.ndarray  # the optimum in s = (log E, nu)
    covariance: np.ndarray  # of s
    noise_std: float
    noise_given: bool
    dof: float  # m - p_eff
    is_E: np.ndarray

    @property
    def std_s(self) -> np.ndarray:
        return np.sqrt(np.maximum(np.diag(self.covariance), 0.0))

    def interval(self, level: float = 1.959964) -> np.ndarray:
        """(n, 2) the 95 % interval of each constant in its own units (E: from log E)."""
        low, high = self.s - level * self.std_s, self.s + level * self.std_s
        return np.stack([np.where(self.is_E, np.exp(low), low), np.where(self.is_E, np.exp(high), high)], axis=1)

    def std(self) -> np.ndarray:
        """Each constant's std in its own units (E: delta method, E sigma_logE)."""
        value = np.where(self.is_E, np.exp(self.s), self.s)
        return np.where(self.is_E, value * self.std_s, self.std_s)

    def correlation(self) -> np.ndarray:
        d = np.where(self.std_s > 0, self.std_s, 1.0)
        return self.covariance / np.outer(d, d)

    def record(self) -> dict:
        """result.json's ``uncertainty``."""
        out = {label: {"std": float(sd), "ci95": [float(lo), float(hi)]}
               for label, sd, (lo, hi) in zip(self.labels, self.std(), self.interval())}
        out["noise_std"] = self.noise_std
        out["noise"] = "given" if self.noise_given else "estimated from the residual"
        out["dof"] = self.dof
        if len(self.labels) > 1:
            out["correlation"] = self.correlation().tolist()
        return out

    def undetermined(self, bounds_s: list) -> list[str]:
        """The constants whose 95 % interval (in s) is wider than their bounds."""
        return [label for label, sd, (lo, hi) in zip(self.labels, self.std_s, bounds_s)
                if not np.isfinite(sd) or 2 * 1.959964 * sd > hi - lo]


def posterior_at(profile, result, noise: float | None = None) -> Posterior | None:
    """The posterior at one of the profile's solves, where the inner solver gave the
    controls' response (Gauss-Newton); None otherwise."""
    lin = profile.linearisation(result)
    if lin is None:
        return None
    s = next(s for s, r, _ in profile.solved if r is result)
    params = profile.params
    return laplace(lin, params.labels, s, params.is_E, noise)


def laplace(lin: Linearisation, labels, s, is_E, noise: float | None = None) -> Posterior:
    """The posterior of s from a Linearisation at the optimum (noise: known std or None)."""
    A = np.hstack([lin.A_q, lin.A_s])
    p = lin.A_q.shape[1]
    prior = np.r_[np.full(p, lin.prior), np.zeros(lin.A_s.shape[1])]
    gram = A.T @ A
    H = gram + np.diag(prior)
    hat = np.trace(np.linalg.lstsq(H, gram, rcond=None)[0])  # tr(A H^-1 A^T): fitted parameters
    dof = max(lin.informative - hat, 1.0)
    noise_std = float(noise) if noise is not None else float(np.sqrt(np.sum(lin.residual**2) / dof))
    Hqq = lin.A_q.T @ lin.A_q + lin.prior * np.eye(p)
    coupling = lin.A_q.T @ lin.A_s
    schur = lin.A_s.T @ lin.A_s - coupling.T @ np.linalg.lstsq(Hqq, coupling, rcond=None)[0]
    covariance = noise_std**2 * _inverse(schur)
    return Posterior(list(labels), np.asarray(s, float), covariance, noise_std, noise is not None, float(dof),
                     np.asarray(is_E, bool))


def _inverse(S: np.ndarray) -> np.ndarray:
    """S^-1 for a symmetric positive semidefinite S; directions S does not see: inf."""
    w, V = np.linalg.eigh((S + S.T) / 2)
    tiny = w <= 1e-14 * max(float(np.abs(w).max()), 1e-300)
    inv = np.where(tiny, np.inf, 1.0 / np.where(tiny, 1.0, w))
    with np.errstate(invalid="ignore"):
        out = (V * inv) @ V.T
    return np.where(np.isnan(out), np.inf, out)
