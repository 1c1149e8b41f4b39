"""Accuracy against independent check points (the paper's Tables 1-2)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.errors import InputError
from ..core.geometry import fit_similarity
from ..io.calibration import Calibration


@dataclass
class CheckpointReport:
    """3D accuracy of adjusted targets against check points.

    Attributes
    ----------
    ids : list of str
        Check points found among the adjusted targets.
    errors : ndarray, shape (K, 3)
        ``adjusted (after the similarity) - check point``, in ``units``.
    rmse_xyz : ndarray, shape (3,)
        RMSE per axis.
    rmse_3d : float
        ``sqrt(mean(|error|^2))``.
    missing : list of str
        Check points with no adjusted target.
    scale : float
        Scale of the fitted 7-parameter similarity.
    """

    ids: list[str]
    errors: np.ndarray
    rmse_xyz: np.ndarray
    rmse_3d: float
    missing: list[str]
    scale: float
    units: str = "m"

    def to_dict(self) -> dict:
        """JSON-ready summary."""
        return {
            "n_checkpoints": len(self.ids),
            "n_missing": len(self.missing),
            "rmse_x": float(self.rmse_xyz[0]),
            "rmse_y": float(self.rmse_xyz[1]),
            "rmse_z": float(self.rmse_xyz[2]),
            "rmse_3d": float(self.rmse_3d),
            "similarity_scale": float(self.scale),
            "units": self.units,
        }


def evaluate_checkpoints(
    target_ids: list[str],
    target_xyz: np.ndarray,
    checkpoint_ids: list[str],
    checkpoint_xyz: np.ndarray,
    units: str = "m",
) -> CheckpointReport:
    """Compare adjusted targets with check points after a 7-parameter similarity.

    Parameters
    ----------
    target_ids : list of str, length T
    target_xyz : ndarray, shape (T, 3)
        Adjusted coordinates.
    checkpoint_ids : list of str, length K
    checkpoint_xyz : ndarray, shape (K, 3)
        Independent survey, same units.

    Returns
    -------
    CheckpointReport

    Raises
    ------
    ValueError
        Fewer than 3 check points among the adjusted targets.
    """
    index = {t: i for i, t in enumerate(target_ids)}
    common = [(k, index[c]) for k, c in enumerate(checkpoint_ids) if c in index]
    missing = [c for c in checkpoint_ids if c not in index]
    if len(common) < 3:
        raise InputError(
            f"only {len(common)} of {len(checkpoint_ids)} check points are adjusted targets; "
            "need at least 3"
        )
    k_idx = np.array([k for k, _ in common])
    t_idx = np.array([i for _, i in common])
    adjusted = np.asarray(target_xyz, float)[t_idx]
    check = np.asarray(checkpoint_xyz, float)[k_idx]
    sim = fit_similarity(adjusted, check)
    err = sim.apply(adjusted) - check
    return CheckpointReport(
        ids=[checkpoint_ids[k] for k in k_idx],
        errors=err,
        rmse_xyz=np.sqrt(np.mean(err**2, axis=0)),
        rmse_3d=float(np.sqrt(np.mean(np.sum(err**2, axis=1)))),
        missing=missing,
        scale=sim.scale,
        units=units,
    )


def evaluate_calibration(calibration: Calibration, checkpoint_ids, checkpoint_xyz, units="m"):
    """:func:`evaluate_checkpoints` on a :class:`Calibration`'s adjusted targets."""
    return evaluate_checkpoints(
        calibration.target_ids, calibration.target_xyz, checkpoint_ids, checkpoint_xyz, units
    )
