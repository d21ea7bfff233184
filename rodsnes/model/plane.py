"""Whether a scene lies in a plane, and which: a plane normal to a coordinate axis holding the
reference, initial and perfect centrelines, one director normal to it at every node, and the
loads and supports (solve/planar.py solves such a scene on its in-plane unknowns; io/scene.py
refuses -rod_planar on for any other)."""
import numpy as np

from rodsnes.model import so3

# a position or director component that is zero in a plane (relative to L, resp. 1)
FLAT = 1e-12
AXES = "xyz"


class Plane:
    """The plane normal to e_axis: in-plane unknowns ``inplane`` (two position components and
    the rotation increment about e_axis), out-of-plane ``outplane`` (the other three);
    ``director``: the index k of the director d_k = +-e_axis."""

    def __init__(self, axis, director):
        self.axis, self.director = int(axis), int(director)
        pos = [c for c in range(3) if c != axis]
        self.inplane = np.array(pos + [3 + axis])
        self.outplane = np.array([axis] + [3 + c for c in pos])
        self.label = "%s-%s" % (AXES[pos[0]], AXES[pos[1]])

    def model(self):
        """The model as summary.json says it, e.g. "planar (x, y, theta per node)"."""
        a, b = self.label.split("-")
        return "planar (%s, %s, theta per node)" % (a, b)


def detect(scene, mesh):
    """(Plane, None) when the scene is planar (module docstring), else (None, why not: the
    part of the scene that leaves the plane, with its option).  Reads the mesh's reference,
    perfect and initial shapes and the scene's loads and supports."""
    rod, ld, bc = scene.rod, scene.loads, scene.bc
    if ld.twist_turns:
        return None, "-load_twist_turns twists the rod about its tangent, out of any plane"
    if bc.end_turns:
        return None, "-bc_end_turns turns the end about its tangent, out of any plane"
    if ld.arclength:
        return None, "-load_arclength continues the branch on the 3-D system"
    L = mesh.length
    shapes = (("reference", mesh.x_ref, mesh.q_ref), ("initial", mesh.x_init, mesh.q_init),
              ("perfect", mesh.x_perfect, mesh.q_perfect))
    why = []
    for axis in (2, 1, 0):                     # the x-y plane first
        reason = _off_plane(axis, shapes, L, rod, ld)
        if isinstance(reason, Plane):
            return reason, None
        why.append(reason)
    return None, why[0]


def _off_plane(axis, shapes, L, rod, ld):
    """The Plane normal to e_axis if the scene lies in it, else why not."""
    name = AXES[axis]
    for what, x, q in shapes[::-1]:              # the perfect shape first
        if np.ptp(x[:, axis]) > FLAT * L:
            return _shape_reason(rod, what, name)
    director = None
    for what, x, q in shapes:
        R = so3.rot(q)                                    # columns: the directors
        normal = np.abs(np.abs(R[:, axis, :]) - 1.0) <= FLAT   # (n, 3): d_k = +-e_axis
        common = np.flatnonzero(normal.all(axis=0))
        if len(common) == 0 or (director is not None and director not in common):
            if rod.twist_turns:
                return "-rod_twist_turns twists the directors out of the plane"
            return "the %s directors do not keep one of them normal to the %s plane" % (
                what, _plane(axis))
        director = int(common[0])
    k = director
    if rod.kappa0 is not None and np.any(np.delete(rod.kappa0, k) != 0.0):
        return ("-rod_kappa0 has a curvature or twist component about an in-plane director "
                "(only k%d, about the plane normal d%d, keeps the rod in the %s plane)"
                % (k + 1, k + 1, _plane(axis)))
    if ld.end_force[axis] != 0.0:
        return "-load_end_force has a component along %s, out of the %s plane" % (name, _plane(axis))
    if ld.gravity[axis] != 0.0:
        return "-load_gravity has a component along %s, out of the %s plane" % (name, _plane(axis))
    if np.any(np.delete(ld.end_moment, axis) != 0.0):
        return ("-load_end_moment has a component about an in-plane axis (only m%s, about the "
                "normal of the %s plane, keeps the rod in it)" % (name, _plane(axis)))
    return Plane(axis, k)


def _plane(axis):
    return "-".join(AXES[c] for c in range(3) if c != axis)


def _shape_reason(rod, what, name):
    if rod.shape == "helix":
        return "-rod_shape helix is not a plane curve"
    if what != "perfect" and rod.imperfection:
        return "-rod_imperfection moves the centreline out of its plane (along %s)" % name
    return "the %s centreline is not in a plane normal to a coordinate axis" % what


def refusal(why):
    """The message of -rod_planar on for a scene that is not planar."""
    return ("-rod_planar on: the scene is not planar: %s; use -rod_planar auto (3-D for this "
            "scene) or off" % why)
