"""The terms of the total energy a scene asks for (model/term.Term), in the order the rod
problem sums them: the external loads, then with -contact the self-contact term (which holds
the clamps' mounts, -contact_supports).  Used by the run and by the error estimate's enriched
problem (solve/estimate.py), which must pose the same scene."""
from rodsnes.contact.term import ContactTerm
from rodsnes.model import fe
from rodsnes.model.loads import Loads


def scene_terms(scene, mesh, layout):
    """The list of terms for ``scene`` on ``mesh``/``layout``."""
    rod = scene.rod
    terms = [Loads(scene.loads, mesh, layout, fe.quadrature_points(rod.quadrature, rod.order))]
    if scene.contact.enabled:
        terms.append(ContactTerm(scene, mesh, layout))
    return terms


def contact_term(terms):
    """The self-contact term of ``terms``, or None (for tools, tests and reports that look
    into it)."""
    return next((t for t in terms if isinstance(t, ContactTerm)), None)
