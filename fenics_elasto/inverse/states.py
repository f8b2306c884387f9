"""Several states of one body as one inverse problem (docs/method.md §10).

Every state is observed by the same operator (the matched nodes, then every state's
landmarks and field samples), so one response J serves them all. The stacked problem
puts the states' rows one after another, and their controls likewise; the response is
block-diagonal, diag(J, ..., J): a state's rows answer its own controls only. One state
is the plain problem (every map below the identity).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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
