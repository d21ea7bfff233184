"""Self-contact terms: the closest-point (projection) law with the candidate search, the pair potential, the parallel term with its star forest (term) and the clamps' mounts."""
