"""Typed engine errors. Their messages are written for the user: operators show them verbatim."""


class LMDPError(Exception):
    """Base class: a problem the user can fix (bad input, missing stage, budget exceeded)."""


class SceneError(LMDPError):
    """The scene cannot be turned into an LMDP (no meshes, no emitter, no UVs, ...)."""


class BudgetError(LMDPError):
    """The requested problem would need more memory than the configured budget."""


class StageOrderError(LMDPError):
    """A step was run before the stage it needs exists ("Build the dynamics first")."""


class Cancelled(LMDPError):
    """The user cancelled a long-running step; nothing was written."""

    def __init__(self, message="Cancelled by the user"):
        super().__init__(message)
