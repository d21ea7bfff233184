"""A rod state carried from one mesh to another (pure math, no PETSc): the finite element
fields evaluated at arbitrary arclengths, and the discretisations an error estimate compares.

Positions are the Lagrange interpolant of the nodes, x_h(s) = sum_a N_a(xi) x_a.  Rotations are
interpolated as the elements do it (elastic.py, METHOD_NOTES.md: projection-based, objective):
with the element's quaternions sign-aligned to its first node,

    p(s) = sum_a N_a(xi) q_a,      q_h(s) = p(s) / |p(s)|,

never componentwise on rotation vectors or matrices.  At a node this returns the nodal value, so
a state carried onto another mesh keeps the values at the nodes both share (the element ends
for order p+1 on the same elements, every old node for h/2), the supports' prescribed values
among them.
"""
from dataclasses import replace

import numpy as np

from rodsnes.model import fe
from rodsnes.model.elastic import align_signs


def locate(mesh, s):
    """Element e and reference coordinate xi in [-1, 1] of the arclengths s (m,) on ``mesh``
    (a point on an element boundary goes to the element on its right, the last one to the last
    element; a closed rod's s is taken modulo L)."""
    s = np.asarray(s, dtype=float)
    if mesh.closed:
        s = np.mod(s, mesh.length)
    h = mesh.h
    e = np.clip(np.floor(s / h).astype(np.int64), 0, mesh.nelem - 1)
    xi = 2.0 * (s - e * h) / h - 1.0
    return e, xi


def _basis(mesh, s):
    e, xi = locate(mesh, s)
    N = fe.lagrange_values(mesh.order, xi)               # (m, p+1)
    return mesh.conn[e], N


def positions_at(mesh, x_nodes, s):
    """x_h(s) (m,3): the Lagrange interpolant of the nodal positions x_nodes (n,3)."""
    conn, N = _basis(mesh, s)
    return np.sum(N[:, :, None] * np.asarray(x_nodes)[conn], axis=1)


def rotations_at(mesh, q_nodes, s):
    """q_h(s) (m,4): the elements' projection-based interpolation of the nodal unit quaternions
    q_nodes (n,4) (module docstring), q0 >= 0."""
    conn, N = _basis(mesh, s)
    qe = align_signs(np.asarray(q_nodes)[conn])          # (m, p+1, 4)
    p = np.sum(N[:, :, None] * qe, axis=1)
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    return np.where(p[:, :1] < 0.0, -p, p)


def transfer(mesh_from, x_nodes, q_nodes, mesh_to):
    """The state (x_nodes, q_nodes) of mesh_from at the nodes of mesh_to: (x (n',3), q (n',4))."""
    s = mesh_to.s_nodes
    return positions_at(mesh_from, x_nodes, s), rotations_at(mesh_from, q_nodes, s)


def sample_points(mesh, per_element=8):
    """Arclengths of a fine sampling of the rod for the centreline error: per_element points
    per element (equispaced, both ends), the end s = L of an open rod included."""
    m = mesh.nelem * per_element
    return np.linspace(0.0, mesh.length, m + (0 if mesh.closed else 1), endpoint=not mesh.closed)


def enriched_rod(rod, order=None, nelem=None):
    """A copy of the scene's Rod with another order and/or element count."""
    return replace(rod, order=rod.order if order is None else int(order),
                   nelem=rod.nelem if nelem is None else int(nelem))


def kept_nodes(mesh_from, mesh_to):
    """(n',) bool: the nodes of mesh_to that are nodes of mesh_from (same arclength within 1e-9
    of an element): the element ends when mesh_to is order p+1 on mesh_from's elements, where
    transfer keeps the nodal values."""
    s_from = np.sort(np.asarray(mesh_from.s_nodes, float))
    s = np.asarray(mesh_to.s_nodes, float)
    i = np.clip(np.searchsorted(s_from, s), 1, len(s_from) - 1)
    gap = np.minimum(np.abs(s - s_from[i - 1]), np.abs(s - s_from[i]))
    return gap <= 1e-9 * min(mesh_from.h, mesh_to.h)
