"""inrslam: neural implicit RGB-D SLAM research framework.

Data flow (and import direction): data -> geometry -> fields -> rendering -> slam -> eval -> bench -> api -> cli.
The API (`inrslam.run`, `load_config`, `evaluate`, `sweep`, `report`, `load_run`; docs in `inrslam.api`) loads on
first use, so `import inrslam` stays light.
"""

from inrslam.omp_env import apply_wait_policy as _apply_wait_policy

__version__ = "0.1.0"

_apply_wait_policy()  # before torch loads OpenMP: adaptive or passive waits (docs/speed.md, shared machines)

_API = ("run", "load_config", "evaluate", "sweep", "report", "load_run", "LoadedRun")
__all__ = ["__version__", *_API]


def __getattr__(name: str):
    if name in _API:
        from inrslam import api

        return getattr(api, name)
    raise AttributeError(f"module 'inrslam' has no attribute {name!r}")
