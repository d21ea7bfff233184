"""Load stepping and the nonlinear solves: energy minimisation (minimize), Newton with cut-back (newton), pseudo-arclength continuation, stability (inertia)."""
