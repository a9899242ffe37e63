"""The contacts' Jacobian H (m constraint rows x 3n) in node form, with its sparse matrix made
only where a compliance mode asks for it.

Row r moves at most four nodes: ``nodes[r, s]`` (-1: none) along ``coef[r, s]`` (the weight of
the node in the tissue point times the row's direction), i.e. H[r] = sum_s e_{nodes[r, s]} (x)
coef[r, s]. This is the form the device factors gather W from
(:meth:`soft_tissue_sim.device_preconditioner.AsyncDevicePreconditioner.delassus_rows`); the
CSR matrix is for the host modes (the block diagonal, the exact compliance, CHOLMOD's
``delassus``).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sps


class ConstraintRows:
    """H in node form (see the module docstring): ``nodes`` (m, 4) int32, ``coef`` (m, 4, 3),
    over ``n_nodes`` nodes."""

    def __init__(self, nodes: np.ndarray, coef: np.ndarray, n_nodes: int):
        self.nodes = nodes
        self.coef = coef
        self.n_nodes = int(n_nodes)
        self._csr: sps.csr_matrix | None = None

    def __len__(self) -> int:
        return len(self.nodes)

    def csr(self) -> sps.csr_matrix:
        """H as a sparse (m, 3n) matrix, made on the first call."""
        if self._csr is None:
            r_i, s_i = np.nonzero(self.nodes >= 0)
            cols = (3 * self.nodes[r_i, s_i].astype(np.int64))[:, None] + np.arange(3)
            self._csr = sps.csr_matrix((self.coef[r_i, s_i].ravel(), (np.repeat(r_i, 3), cols.ravel())),
                                       shape=(len(self.nodes), 3 * self.n_nodes))
        return self._csr

    def transpose_times(self, lam: np.ndarray) -> np.ndarray:
        """H^T lam (3n,): each row's coefficients times its lambda, scattered onto its nodes
        (the forces of the constraints on the nodes), without the sparse matrix."""
        out = np.zeros((self.n_nodes, 3))
        used = self.nodes >= 0
        np.add.at(out, self.nodes[used], (lam[:, None, None] * self.coef)[used])
        return out.reshape(-1)
