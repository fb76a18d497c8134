"""Status of long steps, for whoever shows it: `inrslam run` and `inrslam eval` draw lines and bars; nothing is
shown otherwise (a sweep's workers, scripts, tests), unless the application's `logging` shows INFO records.

Library code reports through the standard `logging` module, on loggers under "inrslam", at level INFO:
`stage(log, text)` when a step starts (a status line), `progress(log, text, done, total)` as a counted step advances
(a bar; the record carries `(done, total)` as its `PROGRESS_ATTR`). Reporting changes nothing a run computes or
writes.
"""

from __future__ import annotations

import logging

LOGGER = "inrslam"  # parent of every logger that reports status
PROGRESS_ATTR = "inrslam_progress"  # LogRecord attribute of `progress` records: (done, total)


def logger(module: str) -> logging.Logger:
    """The status logger of a module (`logger(__name__)`), a child of "inrslam"."""
    return logging.getLogger(module if module.startswith(LOGGER + ".") else f"{LOGGER}.{module}")


def stage(log: logging.Logger, text: str) -> None:
    """A step starts: one status line, e.g. 'extracting the mesh (marching cubes, 2 cm grid)'."""
    log.info(text)


def progress(log: logging.Logger, text: str, done: int, total: int) -> None:
    """A counted step advanced to `done` of `total` (e.g. held-out frames rendered); `text` names the step and
    stays the same while it runs."""
    if log.isEnabledFor(logging.INFO):
        log.info(text, extra={PROGRESS_ATTR: (int(done), int(total))})


def progress_of(record: logging.LogRecord) -> tuple[int, int] | None:
    """(done, total) of a `progress` record, None for a status line."""
    return getattr(record, PROGRESS_ATTR, None)
