"""What one load step of the Newton path (solver.py), or one point of a pseudo-arclength
continuation (arclength.py), reports: shared by both without one importing the other."""


class StepResult:
    """Load factor, converged, Newton iterations, reason (a SNES reason, or a word such as
    "stagnation", "stability", "arclength"), final |F|, the |F| history and seconds; the
    solvers add negative_eigenvalues (-stability), next_increment, arclength flags."""

    def __init__(self, lam, converged, its, reason, fnorm, history, seconds):
        self.lam, self.converged, self.its, self.reason = lam, converged, its, reason
        self.fnorm, self.history, self.seconds = fnorm, history, seconds
