"""When a servo task ends, decided from the controller's iterations alone (no zenoh, no clock): converged, aborted
by its constraints, the target lost (or diverged: lost after the error grew), refused by safety, or out of iterations.
The runner (:func:`services.servo.run.run`) feeds it each iteration as it comes; a timeout and a robot that
stopped are the runner's, being about time and processes."""
from __future__ import annotations

import math
from typing import Optional

from protocol.messages import ControllerState

#: safety refused the law's output this many iterations in a row (a second at the camera's 30 Hz): the arm is held
#: where it is and the law, asking for the same motion, will not get anywhere
REFUSED_ITERATIONS = 30
#: a target lost after the error grew past this multiple of its first value is a divergence, not a lost tag
DIVERGED_ERROR_GROWTH = 2.0


class TerminationRule:
    def __init__(self, target_lost_iterations: int, max_iterations: int,
                 refused_iterations: int = REFUSED_ITERATIONS) -> None:
        self.target_lost_iterations = target_lost_iterations
        self.max_iterations = max_iterations
        self.refused_iterations = refused_iterations
        #: the error of the first iteration the law acted on, and the largest since
        self.initial_error: Optional[float] = None
        self.max_error = -math.inf
        self.lost_streak = 0
        self.refused_streak = 0

    def observe(self, status: ControllerState, error_norm: float, iteration: int, refused: bool) -> Optional[str]:
        """One iteration of the controller (``refused``: safety refused its output); the task's final status if it
        ends here (``converged``, ``constraint_abort``, ``diverged``, ``target_lost``, ``refused``,
        ``max_iterations``), else None."""
        outcome = None
        if status is ControllerState.CONVERGED:
            outcome = "converged"
        elif status is ControllerState.CONSTRAINT_ABORT:
            outcome = "constraint_abort"
        self.lost_streak = self.lost_streak + 1 if status is ControllerState.TARGET_LOST else 0
        if status is ControllerState.CONVERGING:
            self.initial_error = error_norm if self.initial_error is None else self.initial_error
            self.max_error = max(self.max_error, error_norm)
        self.refused_streak = self.refused_streak + 1 if refused else 0
        if self.lost_streak >= self.target_lost_iterations:
            grew = self.initial_error is not None and self.max_error > DIVERGED_ERROR_GROWTH * self.initial_error
            outcome = "diverged" if grew else "target_lost"
        elif self.refused_streak >= self.refused_iterations:
            outcome = "refused"
        elif iteration >= self.max_iterations:
            outcome = "max_iterations"
        return outcome
