"""Lagrange finite elements on a 1-D reference element (pure math, no PETSc).

Reference element xi in [-1, 1] with p+1 equispaced nodes xi_a = -1 + 2a/p.
An element of arclength h maps s = s_e + (xi + 1) h / 2, so ds = (h/2) dxi and
d/ds = (2/h) d/dxi.

    N_a(xi) = prod_{b != a} (xi - xi_b) / (xi_a - xi_b)          (Lagrange basis)
"""
import numpy as np


def gauss_legendre(nq):
    """Gauss-Legendre points and weights on [-1, 1] (exact for degree 2 nq - 1)."""
    if nq < 1:
        raise ValueError("need at least one quadrature point")
    xi, w = np.polynomial.legendre.leggauss(int(nq))
    return xi, w


def reference_nodes(order):
    """Equispaced nodes xi_a = -1 + 2a/p, a = 0..p."""
    return np.linspace(-1.0, 1.0, int(order) + 1)


def lagrange(order, xi):
    """Lagrange basis of degree ``order`` at points ``xi``.

    Returns (N, dN, d2N), each of shape (len(xi), order+1); derivatives are with
    respect to xi (multiply by 2/h, (2/h)^2 for arclength derivatives).
    """
    xi = np.atleast_1d(np.asarray(xi, dtype=float))
    nodes = reference_nodes(order)
    n = len(nodes)
    N = np.ones((len(xi), n))
    dN = np.zeros((len(xi), n))
    d2N = np.zeros((len(xi), n))
    for a in range(n):
        others = [b for b in range(n) if b != a]
        denom = np.prod([nodes[a] - nodes[b] for b in others])
        fac = np.array([xi - nodes[b] for b in others])  # (n-1, nq)
        N[:, a] = np.prod(fac, axis=0) / denom
        for i in range(len(others)):
            rest = np.delete(fac, i, axis=0)
            dN[:, a] += np.prod(rest, axis=0) / denom
            for j in range(len(others)):
                if j == i:
                    continue
                rest2 = np.delete(fac, [i, j], axis=0)
                d2N[:, a] += np.prod(rest2, axis=0) / denom
    return N, dN, d2N


def lagrange_values(order, xi):
    """The Lagrange basis of degree ``order`` at the points ``xi`` alone, (len(xi), order+1):
    lagrange's N without its derivatives (whose products over every pair of the other nodes
    cost 0.1 s for the 8e4 sample points of an error estimate at 10^4 elements)."""
    xi = np.atleast_1d(np.asarray(xi, dtype=float))
    nodes = reference_nodes(order)
    N = np.ones((len(xi), len(nodes)))
    for a, na in enumerate(nodes):
        for b, nb in enumerate(nodes):
            if b != a:
                N[:, a] *= (xi - nb) / (na - nb)
    return N


def quadrature_points(rule, order):
    """Number of Gauss points: 'full' integrates the degree-2p products exactly
    (p+1 points), 'reduced' uses p points (the usual cure for shear/membrane locking)."""
    if rule == "full":
        return order + 1
    if rule == "reduced":
        return max(order, 1)
    raise ValueError(f"unknown quadrature rule {rule!r}: use full or reduced")
