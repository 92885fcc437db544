"""Exceptions the engine raises; callers (CLI, worker) turn them into readable job errors."""


class EngineError(Exception):
    """Base class of every error the engine raises on purpose."""


class SpecError(EngineError, ValueError):
    """The spec is valid field by field but cannot be run (e.g. the particles do not fit)."""


class InstabilityError(EngineError):
    """The run became numerically unstable; the message names the step, the particle and the cause."""

    def __init__(self, message: str, step: int = -1, particle: int = -1):
        super().__init__(message)
        self.step = step
        self.particle = particle


class Cancelled(EngineError):
    """The caller asked the run to stop (cancel check returned True)."""


class BackendUnavailable(EngineError):
    """The requested backend cannot run here (e.g. backend='cuda' without a GPU)."""
