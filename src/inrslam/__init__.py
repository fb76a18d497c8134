"""inrslam: neural implicit RGB-D SLAM research framework.

Data flow (and import direction): data -> geometry -> fields -> rendering -> slam -> eval -> bench -> cli.
"""

from inrslam.omp_env import apply_wait_policy as _apply_wait_policy

__version__ = "0.1.0"

_apply_wait_policy()  # before torch loads OpenMP: passive waits (docs/speed.md, shared machines)
