"""Self-contact: the candidate search (search), the closest-point projection (closest_point,
zones) and its law (projection), the pair-potential law (potential), the parallel term with
its star forest (term) and the clamps' mounts (mounts)."""
