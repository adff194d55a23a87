"""The error a bad parameter raises, apart so that the parameter table and the
plausibility checks can both raise it without importing each other."""

from __future__ import annotations

__all__ = ["ParameterError"]


class ParameterError(ValueError):
    """A parameter value or name breaks a rule; the message names both."""
