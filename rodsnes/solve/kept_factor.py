"""Newton directions through a kept factorisation: K d = -g solved by GMRES preconditioned by
the LU of an earlier iterate's K, a fresh LU only when that stops paying.

Where a load step crawls (hundreds of short Newton steps along a soft mode, each moving the
state by a few thousandths of a radian) the tangent changes little from one iteration to the
next, and its factorisation is most of an iteration.  The last LU then preconditions GMRES on
the new tangent (right preconditioning: the true residual |K d + g| is what converges); a few
Krylov iterations, each a product with K and two triangular solves, replace the factorisation.
The direction is that of the fresh LU to RTOL of |g|: Newton keeps its quadratic end game.

A fresh factorisation is made
- when the matrix is a new one (a new contact pattern) or none was factored yet,
- when GMRES does not reach RTOL within MAX_ITS (the tangent has moved too far: that solve
  is then made by the fresh LU), and
- at the iteration after a solve that took more than REFRESH_ITS Krylov iterations (the next
  solve would take as many again, at about the cost of an LU).

Only where the Newton KSP is rodsnes' direct solve (preonly with a factorisation); a user's
-ksp_type keeps every solve as the user set it."""
from petsc4py import PETSc

RTOL = 1e-6         # relative to |g|: the direction to this of the fresh LU's
MAX_ITS = 10        # Krylov iterations before the solve falls back to a fresh factorisation
REFRESH_ITS = 4     # a solve that took more: the next iteration factors afresh
ENABLED = True


class KeptFactor:
    """The Newton step's linear solve with its factorisation kept (module docstring): ``direct``
    the preonly KSP whose PC factors; ``solve(J, g, d)`` returns (solved, factored)."""

    def __init__(self, direct):
        self.direct = direct
        self.krylov = None
        self.factored = None        # the matrix whose (earlier) factorisation the PC holds
        self.fresh_next = True
        self.krylov_solves = self.krylov_its = self.fallbacks = 0

    def eligible(self):
        pc = self.direct.getPC()
        return (ENABLED and self.direct.getType() == PETSc.KSP.Type.PREONLY
                and pc.getType() in (PETSc.PC.Type.LU, PETSc.PC.Type.CHOLESKY,
                                     PETSc.PC.Type.REDUNDANT, PETSc.PC.Type.PYTHON))

    def _krylov(self):
        if self.krylov is None:
            k = self.krylov = PETSc.KSP().create(comm=self.direct.getComm())
            k.setType(PETSc.KSP.Type.GMRES)
            k.setPCSide(PETSc.PC.Side.RIGHT)
            k.setTolerances(rtol=RTOL, atol=0.0, max_it=MAX_ITS)
            k.setGMRESRestart(MAX_ITS)
        self.krylov.setPC(self.direct.getPC())
        return self.krylov

    def solve(self, J, g, d):
        """d with J d = g (the caller negates); returns (converged, factored afresh)."""
        if self.factored is J and not self.fresh_next and self.eligible():
            k = self._krylov()
            pc = self.direct.getPC()
            pc.setReusePreconditioner(True)
            try:
                k.setOperators(J, J)
                k.solve(g, d)
                ok = k.getConvergedReason() > 0
            except PETSc.Error:
                ok = False
            finally:
                pc.setReusePreconditioner(False)
            its = k.getIterationNumber()
            self.krylov_solves += 1
            self.krylov_its += its
            if ok:
                self.fresh_next = its > REFRESH_ITS
                return True, False
            self.fallbacks += 1
        self.direct.setOperators(J)
        self.factored = None
        self.direct.solve(g, d)
        ok = self.direct.getConvergedReason() >= 0
        self.factored = J if ok else None
        self.fresh_next = False
        return ok, True

    def forget(self):
        """The kept factorisation no longer belongs to the matrix (a new pattern)."""
        self.factored = None

    def destroy(self):
        if self.krylov is not None:
            self.krylov.destroy()
            self.krylov = None
