"""Per-strand contact (ContactKernel.evaluate): E_c = (mu/2) sum_k int <d_k>^2 ds, d_k the gap to
the k-th strand in reach (contact.strand_index), instead of the slides' single closest point
over all strands.  Where a point touches two strands at once and their distances tie, the single
closest point jumps from one to the other and the residual with it; summed per strand it is
smooth, and the point is pushed by both."""
import numpy as np
import pytest

from rodsnes.contact.search import strand_index

from test_contact_math import EPS, check_gradient, check_tangent
from test_contact_zones import exact_energy, waypoint_rod


def test_strand_index_open_rod():
    """Runs of consecutive candidates, numbered per slave element in order of element id; the
    slave's own neighbourhood (e -+ near) joins the run it touches."""
    pairs = np.array([[5, 20], [5, 21], [5, 22], [5, 40], [5, 41], [5, 7],
                      [30, 0], [30, 1], [30, 10], [30, 29]])
    k = strand_index(pairs, 60, closed=False, near=1)
    # slave 5: 4-6 (own, virtual) + 7 -> run 0; 20-22 -> 1; 40-41 -> 2
    # slave 30: 0-1 -> 0; 10 -> 1; 29 (with own 29-31) -> 2
    assert k.tolist() == [1, 1, 1, 2, 2, 0, 0, 0, 1, 2]
    assert strand_index(np.zeros((0, 2)), 60, False).shape == (0,)


def test_strand_index_closed_rod_wraps():
    """On a closed rod a run through the last element and element 0 is one strand (run 0)."""
    pairs = np.array([[30, 58], [30, 59], [30, 0], [30, 1],
                      [0, 30], [0, 31], [0, 58]])
    k = strand_index(pairs, 60, closed=True, near=1)
    # slave 30: 58-59-0-1 one run (0), own 29-31 -> 1
    # slave 0: own 59-0-1 and 58 -> one run through the wrap (0); 30-31 -> 1
    assert k.tolist() == [0, 0, 0, 0, 1, 1, 0]
    # the same pairs on an open rod: 58-59 and 0-1 are two strands (own 29-31 between)
    assert strand_index(pairs[:4], 60, closed=False, near=1).tolist() == [2, 2, 0, 0]


XC = 0.0517            # where B and C cross A: not at a node of A (generic position)


def sandwich(p, g, shift=0.0):
    """A straight strand A along x at z = 0 between two strands crossing it at right angles,
    B along y at z = g and C along y at z = -g - shift (A, B, C of 8, 10, 9 elements; B and C joined by a vertical piece far
    from A, 2 g apart: not touching each other; A joined to B by a bridge far away).  Elements
    of parametric length 0.25.  For eps < g < 2 eps the points of A at the crossing touch B and
    C at once, at equal distance when shift = 0.  B and C cross A at x = XC."""
    x = XC
    W = [(-1, 0, 0), (1, 0, 0), (1, -1.4, 0), (x, -1.4, g), (x, 1.1, g), (x, 1.1, -g - shift),
         (x, -1.15, -g - shift)]
    return waypoint_rod(W, p)


@pytest.mark.slow
@pytest.mark.parametrize("p", [2, 3])
def test_a_point_between_two_strands_is_pushed_by_both(p):
    """A squeezed between B and C: energy = two right-angle crossings (both strands slave in
    each), residual and tangent against differences, and the residual continuous as C moves
    through the tie (|d_B - d_C| = 0): a move of C by 2e-9 changes it by O(1e-9), where the
    single closest point over all strands (evaluate_strand on every candidate) jumps by
    O(mu d) there (A's crossing force switches sides)."""
    g = 1.8 * EPS
    rod, X, nel = sandwich(p, g)
    pairs = rod.pairs(X)
    k = strand_index(pairs, rod.nelem, False, int(np.ceil(rod.delta / rod.h)) + 1)
    a_elems = np.arange(nel[0])
    assert k[np.isin(pairs[:, 0], a_elems)].max() >= 2      # A's crossing elements: own, B, C
    out = rod.eval(X, pairs)
    E = 2 * exact_energy(np.pi / 2, g)
    assert abs(out["energy"] - E) < 1e-8 * E, (out["energy"], E)
    check_gradient(rod, X, pairs, 1e-7, tol=1e-6, maxrows=12)
    check_tangent(rod, X, pairs, 1e-8, tol=1e-6, maxcols=16)     # measured 7e-9 (p = 3)

    nA = nel[0] * p + 1                                    # A's nodes come first

    def residual_of_A(shift, single):
        r2, X2, _ = sandwich(p, g, shift)
        if single:
            r2.k.evaluate = r2.k.evaluate_strand
        return r2.residual(X2, r2.pairs(X2))[:nA]

    jumps = []
    for single in (False, True):
        Rm, Rp = residual_of_A(-1e-9, single), residual_of_A(1e-9, single)
        jumps.append(np.abs(Rp - Rm).max())
    scale = np.abs(Rp).max()
    # measured (p = 3): summed 5e-10 (the smooth change over 2e-9), single 3.3e-3 = 2 x the
    # largest nodal force (the push on A flips from -z to +z)
    assert jumps[1] > 0.3 * scale, jumps              # the slides' single min: a jump
    assert jumps[0] < 1e-5 * scale, jumps             # summed per strand: smooth
