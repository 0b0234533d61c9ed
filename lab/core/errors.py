"""Errors shared across layers.  A `UserError` is the user's to fix (bad file, bad argument,
out-of-range request): the CLI prints it in one line without a traceback and exits with 2."""


class LabError(Exception):
    """Base of every error `lab` raises on purpose."""


class UserError(LabError):
    """Bad input: a rig file, scenario, argument or command the user can correct."""
