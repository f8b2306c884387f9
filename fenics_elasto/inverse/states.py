"""Several states of one body as one inverse problem (docs/method.md §10).

Every state is observed by the same operator (the matched nodes, then every state's
landmarks and field samples), so one response J serves them all. The stacked problem
puts the states' rows one after another, and their controls likewise; the response is
block-diagonal, diag(J, ..., J): a state's rows answer its own controls only. One state
is the plain problem (every map below the identity).

Each state's target may state its own noise (``[target] noise``: one scan segmented
better than another). The states' rows are then weighed by it, by maximum likelihood:
w_k = (sigma_ref / sigma_k)^2 with sigma_ref the smallest, so that Phi / sigma_ref^2 is
the negative log-likelihood of them all and the posterior's noise is sigma_ref, given.
A noise stated for some states and not for others is refused: an estimated level for
the rest would have to come from residuals already weighed by the stated ones.
Without any, the states' residuals give one noise level together, and weigh alike
(the inclusion with one outline displaced by 200x the other's noise: E dragged to its
bound; with both noises stated, within 1.5 %, tests/verification/test_more_than_surfaces.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fenics_elasto.util.errors import require


@dataclass
class States:
    """The states' names, their misfits (each over the observation's rows) and their
    [target] tables; one state named "" for a plain [target]."""

    names: list[str]
    misfits: list
    specs: list[dict]

    @property
    def count(self) -> int:
        return len(self.names)

    @property
    def noise(self) -> float | None:
        """The noise std Phi is measured in: the smallest stated noise (the one state's
        own), or None where no state states one (estimated from the residual)."""
        stated = self._stated_noise()
        return None if stated is None else min(stated)

    @property
    def weights(self) -> np.ndarray:
        """Each state's rows' weight, (noise / its stated noise)^2; 1 without stated noises."""
        stated = self._stated_noise()
        return np.ones(self.count) if stated is None else (min(stated) / np.asarray(stated)) ** 2

    def _stated_noise(self) -> list[float] | None:
        given = [spec.get("noise") for spec in self.specs]
        if all(g is None for g in given):
            return None
        missing = [name for name, g in zip(self.names, given) if g is None]
        require(not missing, f"[[states]]: target.noise is stated for some states but not for {missing}: "
                             "state it for every state, or for none (one level is then estimated from all)")
        return [float(g) for g in given if g is not None]

    def split(self, stacked: np.ndarray) -> list[np.ndarray]:
        """Rows (or a flat control vector) cut into the states' equal parts."""
        return np.split(stacked, self.count)

    def stack_controls(self, J: np.ndarray) -> np.ndarray:
        """(n, gdim, k) responses of one state's controls -> (S n, gdim, S k), block-diagonal."""
        if self.count == 1:
            return J
        n, gdim, k = J.shape
        out = np.zeros((self.count * n, gdim, self.count * k))
        for i in range(self.count):
            out[i * n:(i + 1) * n, :, i * k:(i + 1) * k] = J
        return out

    def to_motion(self, basis: np.ndarray | None, q: np.ndarray) -> np.ndarray:
        """Every state's loaded-node displacement from its controls (W q_s, or q_s itself)."""
        return q if basis is None else np.concatenate([basis @ qs for qs in self.split(q)])

    def to_controls(self, basis: np.ndarray | None, d: np.ndarray) -> np.ndarray:
        """Every state's controls from its loaded-node displacement (W^T d_s, or d_s)."""
        return d if basis is None else np.concatenate([basis.T @ ds for ds in self.split(d)])

    def distances(self, residual: np.ndarray) -> dict[str, dict]:
        """Each state's distances, from its own rows."""
        return {name: misfit.distances(rows) for name, misfit, rows in zip(self.names, self.misfits, self.split(residual))}
