"""inrslam: neural implicit RGB-D SLAM research framework.

Data flow (and import direction): data -> geometry -> fields -> rendering -> slam -> eval -> bench -> cli.
"""

__version__ = "0.1.0"
