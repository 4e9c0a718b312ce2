"""Exceptions with messages a user can act on. Every error the core raises on bad
input derives from `DiffshegError`; the CLI and the add-on print its message alone."""


class DiffshegError(Exception):
    """A problem the user can fix: the message names it and says how."""


class AudioError(DiffshegError):
    """The audio input is missing, unreadable, or unusable."""


class CheckpointError(DiffshegError):
    """A checkpoint file cannot be read or does not match the model."""


class Cancelled(DiffshegError):
    """Generation was cancelled by the caller between two diffusion steps."""


class AudioWarning(UserWarning):
    """The audio is usable but not what its file says (e.g. a header promising more data)."""
