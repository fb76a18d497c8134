"""Exception types. Every message names the file / key / frame and what was expected."""


class InrslamError(Exception):
    """Base class for errors a user can fix (bad input, bad config)."""


class DataError(InrslamError):
    """Missing, unreadable or inconsistent dataset files."""


class ConfigError(InrslamError):
    """Unknown keys, wrong types or invalid values in a configuration."""


class RunError(InrslamError):
    """A run directory that cannot be written or resumed (corrupt checkpoint, full disk, another run's files)."""


class TrackingLost(InrslamError):
    """Tracking stayed lost for `slam.lost.stop_after` frames (the run stops; finished work is checkpointed)."""


class InrslamWarning(UserWarning):
    """Something a user should know that does not stop the run (the CLI prints it as one line)."""
