"""mocaptk — facial optical motion capture: dense sessions to optimized marker layouts and rigs.

Stages are subpackages: :mod:`mocaptk.acquisition` (files, cameras, triangulation, cleaning),
:mod:`mocaptk.clustering` (regions, correlation, layouts), :mod:`mocaptk.retarget`
(weights, rig exports, guides). This package holds what they share.
"""

from .errors import InputFileError, MocaptkError, OptionError, OutputError
from .trajectories import GapStats, Take, Trajectories, concatenate_takes

__version__ = "0.1.0"

__all__ = [
    "GapStats", "InputFileError", "MocaptkError", "OptionError", "OutputError", "Take",
    "Trajectories", "__version__", "concatenate_takes",
]
