"""The scales a residual is measured against: the forces an equilibrium is made of, and the
round-off floor of the discrete residual."""
import math

import numpy as np


def force_scale_terms(scene):
    """The terms of force_scale by name: bending (EI/L^2), end_force (|F|), end_moment
    (|M|/L), gravity (|g| L), turns (GJ 2 pi (|T_end| + |T_twist|) / L^2: the twisting moment
    of the prescribed turns -bc_end_turns and of the twist load -load_twist_turns, over L).
    hypot, not a 2-norm of squares, so that a problem scaled by 1e-200 keeps its scale."""
    r, ld = scene.rod, scene.loads
    L = r.length
    turns = abs(float(getattr(scene.bc, "end_turns", 0.0) or 0.0)) + abs(float(ld.twist_turns or 0.0))
    return {"bending": max(r.EI1, r.EI2) / L ** 2, "end_force": math.hypot(*ld.end_force),
            "end_moment": math.hypot(*ld.end_moment) / L, "gravity": math.hypot(*ld.gravity) * L,
            "turns": r.GJ * 2.0 * math.pi * turns / L ** 2}


def force_scale(scene):
    """F_scale = EI/L^2 + |F| + |M|/L + |g| L + GJ 2 pi (|T_end| + |T_twist|) / L^2
    (force_scale_terms): the forces the equilibrium is made of, to which the residual is
    compared (Run.force_scale)."""
    return sum(force_scale_terms(scene).values())


def residual_floor(rod):
    """Roundoff floor of the residual: 3 eps x (largest stretch/shear stiffness + largest
    bending/twist stiffness / L) x nodes x sqrt(nodes) (the Newton solver's floor)."""
    n = rod.nelem * rod.order + (0 if rod.closed else 1)
    stiff = max(rod.EA, rod.GA1, rod.GA2) + max(rod.EI1, rod.EI2, rod.GJ) / rod.length
    return 3 * np.finfo(float).eps * stiff * rod.nelem * rod.order * math.sqrt(n)
