"""The one interface every term of the total energy implements (DESIGN.md "terms").

The rod problem (problem.RodProblem) is the rod's strain energy plus a list of terms,

    E(x; lambda) = E_elastic(x; lambda) + sum_t E_t(x; lambda),

that the run builds from the scene (run.scene_terms: the external loads, and with
-contact the self-contact term, which holds the clamps' mounts).  The problem sums them and
knows none by name; the solvers ask the problem, which asks its terms.  A term contributes

  the equations    its share of the energy, the residual dE_t/dx and the tangent d2E_t/dx2 on
                   this rank's local nodes (r positions, q rotations), at load factor lambda;
  a matrix pattern the dof couplings beyond the elements (contact pairs), which may follow the
                   state: the Jacobian is preallocated for them and made anew when they grow;
  step limits      what a Newton step may do near it: the largest move of the nodes it watches,
                   the deepest penetration it admits, the free space between strands;
  a promise        a penalty that keeps a promised penetration by raising its stiffness;
  a report         its section of summary.json and its result.h5 attributes.

Every method has a default that contributes nothing, so a term implements only what it has;
the class attributes say which parts it has (the problem reads them once)."""
import numpy as np


class Term:
    """One part of the total energy.  Local methods act on this rank's share; the ones marked
    collective must be called on every rank."""

    name = None                 # its section of summary.json, prefix of result.h5 attributes
    conservative = True         # has a potential: the energy is a merit function for its steps
    depends_on_load = False     # its residual changes with lambda (arclength: dF/dlambda)
    moving_pattern = False      # couples dofs beyond the elements, in a pattern that follows the state
    positions_only = False      # couples its pattern's node groups by their positions only
    step_limit = None           # largest move per Newton step of the nodes it watches (None: none)
    length_scale = None         # the smallest length it resolves (the contact radius)
    keeps_link = False          # strands cannot pass through each other: the link is conserved
    adapt = False               # raises its penalty to keep its promise (promised_penalty)
    # owner computes: its residual and tangent rows of this rank's own nodes are complete
    # from this rank alone, and its rows of other ranks' nodes are not needed (the problem
    # drops them); False: those rows are summed into their owners' (a reverse scatter of the
    # residual, the Jacobian's stash), the problem's elastic rows then dropped from them
    owner_computes = False

    # -- the equations (local shares; r (n_local, 3), q (n_local, 4)) --------------------
    def energy_local(self, lam, r, q):
        """This rank's share of E_t."""
        return 0.0

    def add_residual(self, lam, r, q, Floc):
        """dE_t/dx into the local node rows Floc (n_local, 6) (owner_computes: the owned
        rows whole, the ghost rows ignored)."""

    def add_jacobian(self, lam, r, q, P, symmetric=False):
        """d2E_t/dx2 into the global matrix P (ADD_VALUES); ``symmetric``: the chart Hessian of
        the energy (stability), which leaves out what has no potential."""

    def trial(self, lam, r, q):
        """(energy share, deepest penetration on this rank or None) at a line-search trial,
        from one evaluation.  Collective for terms that communicate."""
        return self.energy_local(lam, r, q), None

    # -- matrix pattern -------------------------------------------------------------------
    def pattern(self, r):
        """What the Jacobian must be preallocated for at positions r (None: the elements
        suffice); compared with np.array_equal.  Collective."""
        return None

    def node_groups(self, pattern):
        """Natural node groups (n, k) coupled all-to-all by ``pattern`` (None: none)."""
        return None

    def pattern_covers(self, r, pattern):
        """Whether ``pattern`` holds every coupling of the tangent at r.  Collective."""
        return True

    def covering_pattern(self, r):
        """A pattern that holds every coupling of the tangent at r.  Collective."""
        return self.pattern(r)

    # -- step limits ----------------------------------------------------------------------
    def watched_nodes(self, r=None):
        """Owned nodes whose move per Newton step step_limit bounds (at r: evaluated there;
        None: at the last evaluation)."""
        return np.zeros(0, dtype=np.int64)

    def clearance(self, r):
        """A lower bound of the free space between strands at r (inf: no bound).  Collective."""
        return np.inf

    def deepest(self, r=None, report=True):
        """The deepest penetration over all ranks at r (None: the last evaluation), or None
        where the term has no such measure.  Collective."""
        return None

    def depth_allowed(self, depth):
        """The deepest penetration a step may reach from a state whose deepest is ``depth``."""
        return np.inf

    # -- the penalty's promise (adapt) ----------------------------------------------------
    def promised_penalty(self, r):
        """(measure, the penalty that keeps the promise or None while it is kept).  Collective."""
        return 0.0, None

    def ease_wall(self, r, lam):
        """After a converged step at load lam that keeps the promise, once it is written
        (RodProblem.ease_walls): the penalty raised for the next step where a wall holds the
        promise by pressing on it; the line that says so, or None when nothing was raised.
        Collective."""
        return None

    def adopt(self, other):
        """Take what ``other``, the same term of another discretisation of the scene, has
        adapted during its run (the raised penalty), so that both pose the same problem."""

    # -- report ---------------------------------------------------------------------------
    def restart(self, attrs):
        """Take what a restart needs from the result.h5 attributes of the step it starts from."""

    def refuses(self, r):
        """Why the term cannot start from the positions r (local nodes), as a sentence naming
        the option that would let it, or None.  Collective."""
        return None

    def report(self, r):
        """Its section of summary.json at positions r (collective); {} for none."""
        return {}

    def qp_fields(self):
        """Quadrature-point fields of the last report for result.h5 ({ids, n, fields}) or None."""
        return None

    def run_summary(self, stats):
        """The run's counters for its section of summary.json (``stats``: the problem's)."""
        return {}

    def log_text(self):
        """What the step's log line adds ("" for nothing)."""
        return ""

    def describe(self):
        """What the run's first line says of it, e.g. the law it uses ("" for nothing)."""
        return ""


def same_patterns(a, b):
    """Whether two lists of the terms' patterns (RodProblem.patterns; b may be None: none yet)
    are the same, term by term (None, or equal arrays)."""
    return b is not None and len(a) == len(b) and all(
        (x is None and y is None) or (x is not None and y is not None and np.array_equal(x, y))
        for x, y in zip(a, b))
