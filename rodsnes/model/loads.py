"""External loads, all scaled by the load factor lambda (slides "Discretization of the
virtual work of external loads": F_ext = lambda int [f phi_n; c phi_n] ds).

Sign convention: residual = internal - external, so an applied force f enters as -lambda f.
  dead end force      -lambda f                 on the end node's position row
  follower end force  -lambda R_end R_end0^T f  (turns with the end);  d/dtheta_end = +lambda (R_end R_end0^T f)^x
  end moment          -lambda m                 (spatial, dead) on the end node's theta row
  gravity             -lambda int N_a g ds      (force per unit length, consistent nodal forces)
Potential energy of the conservative ones: -lambda f . r_end - lambda int g . r ds.
Loads is a term of the problem (model/term.Term): residual, the follower force's tangent block,
the potential as its energy share.
"""
import numpy as np
from petsc4py import PETSc

from rodsnes.model import fe, so3
from rodsnes.model.term import Term


class Loads(Term):
    """The external loads of the scene (``loads``: scene.loads) as a term; ``nq`` Gauss points
    per element for gravity."""

    depends_on_load = True
    owner_computes = True       # the end's loads on its owner; gravity over layout.row_elems

    def __init__(self, loads, mesh, layout, nq):
        self.conservative = nonconservative(loads) is None
        self.f = np.asarray(loads.end_force, float)
        self.follower = bool(loads.end_force_follower)
        self.m = np.asarray(loads.end_moment, float)
        self.g = np.asarray(loads.gravity, float)
        self.end = None if mesh.closed else mesh.n_nodes - 1
        lay = layout
        self.end_local = None
        if self.end is not None and lay.nat2local[self.end] >= 0 and lay.nat2local[self.end] < lay.n_owned:
            self.end_local = int(lay.nat2local[self.end])
        self.R_end0 = so3.rot(mesh.q_init[-1]) if self.end is not None else None
        self.active = bool(np.any(self.f) or np.any(self.m) or np.any(self.g))
        if np.any(self.g):
            xi, w = fe.gauss_legendre(nq)
            N, _, _ = fe.lagrange(mesh.order, xi)
            self.gravity_weights = (w * mesh.h / 2.0) @ N            # int N_a ds per element node
        else:
            self.gravity_weights = None
        self.lconn = layout.lconn           # the owned elements: the potential
        self.row_lconn = layout.row_lconn   # every element of an owned node: the residual
        self.layout = layout

    def end_force(self, q_end):
        if self.follower:
            return so3.rot(q_end) @ (self.R_end0.T @ self.f)
        return self.f

    def add_residual(self, lam, r_loc, q_loc, Floc):
        if lam == 0.0 or not self.active:
            return
        if self.end_local is not None:
            i = self.end_local
            Floc[i, 0:3] -= lam * self.end_force(q_loc[i])
            Floc[i, 3:6] -= lam * self.m
        if self.gravity_weights is not None:
            np.add.at(Floc[:, 0:3], self.row_lconn,
                      -lam * self.gravity_weights[None, :, None] * self.g)

    def add_jacobian(self, lam, r_loc, q_loc, P, symmetric=False):
        """The follower force's blocks into P (none in the energy's Hessian: no potential)."""
        if symmetric:
            return
        lg = self.layout.nat2petsc[self.layout.local_nodes]
        for i, j, B in self.add_jacobian_blocks(lam, q_loc):
            P.setValuesBlockedRCV(np.array([[lg[i]]], dtype=PETSc.IntType),
                                  np.array([[lg[j]]], dtype=PETSc.IntType), B[None],
                                  addv=PETSc.InsertMode.ADD)

    def energy_local(self, lam, r_loc, q_loc):
        """The potential of the conservative loads on this rank (potential)."""
        return self.potential(lam, r_loc)

    def add_jacobian_blocks(self, lam, q_loc):
        """Extra blocks (local node row, local node col, 6x6) of non-conservative loads."""
        if lam == 0.0 or not self.follower or self.end_local is None or not np.any(self.f):
            return []
        B = np.zeros((6, 6))
        B[0:3, 3:6] = lam * so3.hat(self.end_force(q_loc[self.end_local]))
        return [(self.end_local, self.end_local, B)]

    def potential(self, lam, r_loc):
        """-lambda (f . r_end + int g . r ds) on this rank (conservative parts only)."""
        if lam == 0.0:
            return 0.0
        P = 0.0
        if self.end_local is not None and not self.follower:
            P -= lam * float(self.f @ r_loc[self.end_local])
        if self.gravity_weights is not None:
            P -= lam * float(np.einsum("a,eai,i->", self.gravity_weights, r_loc[self.lconn], self.g))
        return P


def takes_newton_path(loads):
    """Whether the load path is Newton's: asked for (-load_path newton), or chosen by
    -load_path auto for loads without a potential or with -load_arclength."""
    return loads.path == "newton" or (loads.path == "auto" and (
        nonconservative(loads) is not None or bool(loads.arclength)))


def nonconservative(loads):
    """Why energy is not a merit function for these loads (None if it is)."""
    if getattr(loads, "end_force_follower", False) and np.any(np.asarray(loads.end_force)):
        return "the follower end force is not conservative, so energy cannot guide the relaxation"
    if np.any(np.asarray(getattr(loads, "end_moment", (0, 0, 0)))):
        return ("a dead end moment is not conservative for 3-D rotations (and has no potential "
                "here), so energy cannot guide the relaxation")
    return None
