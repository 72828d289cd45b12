"""What one call of a model's step may change about how it integrates: StepOptions.

The stability guard retries a step with a shorter dt, more Newton iterations or implicit
fictitious forces, and the Simulator sweeps fast colliders in sub-steps. Both pass these
options to `model.step(..., options=...)` instead of changing the model's settings and
restoring them afterwards: the settings a scene configured stay as they are, whatever
happens inside a step.
"""
from dataclasses import dataclass, replace


@dataclass(frozen=True)
class StepOptions:
    """dt: length of this step (None: the model's dt). newton_iterations: at least this
    many (None: the model's own). fictitious: "implicit" integrates a reduced model's
    fictitious forces implicitly for this step (None: the model's setting; models without
    moving frames ignore it)."""

    dt: float = None
    newton_iterations: int = None
    fictitious: str = None

    def split(self, dt, n):
        """The options of one of n equal sub-steps of a step of length dt."""
        return replace(self, dt=float(dt) / n)
