"""Map files: a ``dataset@1`` / ``@2`` with optional initial poses in, a calibration-format map out.

``gtsam-sphere refine`` reads the observations of a mapped sequence from a
``dataset@1`` file (``../shared/spec/dataset.md``). An image may carry its
starting pose as an optional ``cam_from_world`` ``{"R": 3x3, "t": [3]}``
(``p_cam = R @ p_world + t``, the dataset's units), e.g. from a SLAM front end;
images without one are posed by resection against the targets' approximate
coordinates. A rig's map is a ``dataset@2`` (images name their camera and
frame). The refined map is written as a ``calibration@1`` document (``@2`` for
a rig, with each frame's ``rig_from_world``): the frozen camera(s) unchanged,
``images[].cam_from_world`` and ``targets[].xyz`` refined, ``statistics`` of
the refinement, so ``load_calibration`` and ``gtsam-sphere evaluate`` read it
as they read a calibration.
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from .calibration import _pose
from .dataset import (
    Dataset,
    RigDataset,
    dataset_version,
    parse_dataset,
    parse_rig_dataset,
    read_json,
)

__all__ = ["load_map"]


def load_map(
    path: str | os.PathLike,
) -> tuple[Dataset | RigDataset, dict[str, tuple[np.ndarray, np.ndarray]]]:
    """Read a map: its observations and the initial poses its images give.

    Parameters
    ----------
    path : path-like
        A ``gtsam-sphere/dataset@1`` or ``dataset@2`` file.

    Returns
    -------
    dataset : Dataset or RigDataset
    initial_cam_from_world : dict
        Image id -> ``(R (3, 3), t (3,))`` ``cam_from_world`` for the images that
        carry one.

    Raises
    ------
    DatasetError
        Not a dataset, or a bad pose (naming the image).
    """
    source = str(path)
    doc: Any = read_json(path)
    if dataset_version(doc, source) == 2:
        dataset = parse_rig_dataset(doc, source)
    else:
        dataset = parse_dataset(doc, source)
    poses = {}
    for im in doc.get("images", []):
        if isinstance(im, dict) and "cam_from_world" in im:
            iid = str(im.get("id"))
            poses[iid] = _pose(im["cam_from_world"], f"image {iid!r} cam_from_world", source)
    return dataset, poses
