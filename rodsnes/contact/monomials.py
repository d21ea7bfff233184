"""Lagrange elements in monomial form, for the closest-point law's polynomial work (pure numpy).

The shape functions of order p (``rodsnes.model.fe``) are N_a(xi) = sum_k C[k, a] xi^k
(``monomial_matrix``), so an element's centreline is r(xi) = sum_k A_k xi^k with A = C^T x,
x its nodes: the form in which the closest-point projection (contact/closest_point.py)
samples, differentiates and finds the roots of the distance polynomial, and in which the law
(contact/projection.py) and the zone segmentation (contact/zones.py) evaluate N, N', N'' at
many points by one matrix product (``monomials``, ``powers``).
"""
import numpy as np

from rodsnes.model import fe

__all__ = ["monomial_matrix", "monomials", "powers"]

_POWER_TABLES = {}


def monomial_matrix(order):
    """C (p+1, p+1) with N_a(xi) = sum_k C[k, a] xi^k."""
    nodes = fe.reference_nodes(order)
    V = nodes[:, None] ** np.arange(order + 1)[None, :]
    return np.linalg.inv(V)


def monomials(order, xi):
    """xi^k, d/dxi xi^k, d2/dxi2 xi^k for k = 0..p: three (len(xi), p+1) arrays."""
    W = powers(order, np.asarray(xi, dtype=float), 2)
    return W[:, 0], W[:, 1], W[:, 2]


def _power_tables(order):
    """Exponents E[j, k] = max(k - j, 0) and factors F[j, k] = k! / (k - j)! (0 for k < j) of
    d^j/dxi^j xi^k = F[j, k] xi^E[j, k], j = 0, 1, 2, k = 0..p."""
    if order not in _POWER_TABLES:
        k = np.arange(order + 1)
        E = np.stack([k, np.maximum(k - 1, 0), np.maximum(k - 2, 0)])
        F = np.stack([np.ones(order + 1), k, k * (k - 1)]).astype(float)
        _POWER_TABLES[order] = E, F
    return _POWER_TABLES[order]


def powers(order, x, nder):
    """d^j/dxi^j xi^k for k = 0..p, j = 0..nder (nder <= 2) at the points x (any shape):
    (x.shape, nder + 1, p + 1); xi^k by repeated products (a cumulative product)."""
    pw = np.empty(x.shape + (order + 1,))
    pw[..., 0] = 1.0
    if order:
        pw[..., 1:] = x[..., None]
        np.multiply.accumulate(pw, axis=-1, out=pw)
    if nder == 0:
        return pw[..., None, :]
    E, F = _power_tables(order)
    return F[:nder + 1] * pw[..., E[:nder + 1]]
