"""gtsam_sphere: calibrate any central camera on a virtual sphere, in a GTSAM graph.

Pipeline, one module per stage: :mod:`dataset` (data contract) ->
:mod:`initialize` (P3P + RANSAC) -> :mod:`graph` (factors) ->
:mod:`optimize` (LM / dogleg) -> :mod:`correct` (kNN corrections) ->
:mod:`evaluate` (check points) -> report.

Warnings and diagnostics go to the ``gtsam_sphere`` logger (module loggers below
it); progress goes to the ``progress`` callbacks. The library adds only a
``NullHandler``: configure :mod:`logging` to see them (the command line installs
a standard-error handler).
"""

import logging

from .core.camera import Model, SphereCamera
from .core.errors import GtsamSphereError, InputError
from .io.calibration import Calibration, RigCalibration, load_calibration
from .io.dataset import (
    Dataset,
    DatasetError,
    RigDataset,
    load_checkpoints,
    load_dataset,
    load_rig_dataset,
)

__all__ = [
    "Calibration",
    "Dataset",
    "DatasetError",
    "GtsamSphereError",
    "InputError",
    "Model",
    "RigCalibration",
    "RigDataset",
    "SphereCamera",
    "load_calibration",
    "load_checkpoints",
    "load_dataset",
    "load_rig_dataset",
]
__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())
