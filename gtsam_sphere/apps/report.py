"""A calibration report: PNG plots, a Markdown page and an HTML page.

:func:`write_report` reads a ``gtsam-sphere/calibration@1`` file (or takes a
:class:`~gtsam_sphere.io.calibration.Calibration`) and writes into ``out_dir``:

``residuals_2d.png``
    Scatter of the image residuals (x, y), outliers in another colour
    (Chow et al. 2018, Fig. 6 and 9).
``histograms.png``
    Histograms of the x and y residuals with a fitted Gaussian (Fig. 7, 10, 11).
``radial.png``
    Residual components against the radial distance from the principal point,
    with the fitted linear trend (Fig. 12).
``convergence.png``
    Cost per iteration (Fig. 5) and the cross-validation score of the
    correction loop when the history has one.
``coverage.png``
    Observation positions in the image frame, the principal point, the
    90-degree incidence curve and the model's measurement correction field.
``residual_field.png``
    Mean residual vector per grid cell: the systematic error left.
``uncertainty.png``
    Projection uncertainty over the image (px) propagated from the
    covariance of the intrinsics, after the camera rotation that best
    re-aligns the image over the observations (the part of the intrinsics'
    error the poses absorb is not counted), plus the local term of a learned
    kNN correction (:mod:`gtsam_sphere.analysis.uncertainty`).
``report.md`` and ``index.html``
    The same tables and images as a Markdown page and an HTML page.

Every PNG is always written; a plot whose data is missing from the file (no
history, no observations, no correction) says so in the image instead.
Residuals are ``measured - predicted`` in pixels, as in the calibration file.
"""

from __future__ import annotations

import argparse
import html
import math
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.robust import mad_sigma
from ..io.calibration import Calibration, RigCalibration, load_calibration

#: The plot files of a report, in page order, with their captions.
PLOTS: dict[str, str] = {
    "residuals_2d": "2D distribution of the image residuals (Chow et al. 2018, Fig. 6/9).",
    "histograms": "Histograms of the x and y image residuals with a fitted Gaussian "
    "(Fig. 7/10/11).",
    "radial": "Image residuals as a function of radial distance from the principal point, "
    "with the fitted linear trend (Fig. 12).",
    "convergence": "Cost after each iteration (Fig. 5) and the cross-validation score of the "
    "correction loop if there was one.",
    "coverage": "Image coverage: observations, principal point, 90 deg incidence curve and "
    "the model's measurement correction field.",
    "residual_field": "Mean residual vector per image cell: systematic error left by the model.",
    "uncertainty": "Projection uncertainty: standard deviation (px) of the pixel of a ray at "
    "infinity, propagated from the covariance of the intrinsics after the camera rotation that "
    "best re-aligns the image over the observations (plus the kNN correction's local term).",
}

#: Observations with a robust weight below this are drawn as outliers.
OUTLIER_WEIGHT = 0.5
#: Number of down-weighted observations listed on the page.
TOP_DOWNWEIGHTED = 20

# statistics rows of the page, in order, with a description
_STAT_ROWS: tuple[tuple[str, str], ...] = (
    ("rms_px", "RMS of the image residuals (px)"),
    ("rms_px_without_outliers", "RMS without outliers (px)"),
    ("n_observations", "observations used"),
    ("n_rejected", "observations rejected before the adjustment"),
    ("n_downweighted", "observations down-weighted by the robust loss"),
    ("n_outliers", "outliers (> 5 sigma, unlike their neighbours)"),
    ("n_systematic", "systematic (> 5 sigma, like their neighbours)"),
    ("n_images", "images used"),
    ("n_images_skipped", "images skipped"),
    ("n_targets", "targets observed"),
    ("sigma_px", "image noise sigma (px)"),
    ("loss", "robust loss"),
    ("loss_threshold", "robust loss threshold (sigma)"),
    ("cost", "final cost"),
    ("weighted_sum_squares", "weighted sum of squares"),
    ("redundancy", "redundancy"),
    ("mean_redundancy", "mean redundancy number"),
    ("n_targets_off_prior", "targets beyond 5 sigma of their priors"),
    ("target_shift_max_sigma", "largest target shift (sigmas of its prior)"),
    ("variance_factor", "a-posteriori variance factor"),
    ("max_incidence_deg", "largest incidence angle (deg)"),
    ("fov_deg", "field of view covered (deg)"),
    ("n_beyond_90deg", "observations beyond 90 deg incidence"),
    ("iterations", "iterations"),
    ("status", "optimizer status"),
    ("converged", "converged"),
    ("datum", "datum"),
)


# --------------------------------------------------------------------------- data


@dataclass
class Observations:
    """Per-observation arrays of a calibration (``extra["observations"]``).

    Attributes
    ----------
    image, target : ndarray of str, shape (N,)
    uv_px : ndarray, shape (N, 2)
        Measured pixels.
    residual_px : ndarray, shape (N, 2)
        ``measured - predicted`` (px).
    weight : ndarray, shape (N,)
        Robust weights (1 where the file has none).
    incidence_deg : ndarray, shape (N,)
        NaN where the file has none.
    """

    image: np.ndarray
    target: np.ndarray
    uv_px: np.ndarray
    residual_px: np.ndarray
    weight: np.ndarray
    incidence_deg: np.ndarray

    def __len__(self) -> int:
        return len(self.residual_px)

    @property
    def outlier(self) -> np.ndarray:
        """Boolean (N,): robust weight below :data:`OUTLIER_WEIGHT`."""
        return self.weight < OUTLIER_WEIGHT


def observations_of(calib: Calibration) -> Observations | None:
    """The observation arrays of ``calib``, or ``None`` if the file has none usable."""
    obs = calib.extra.get("observations")
    if not isinstance(obs, dict) or "residual_px" not in obs:
        return None
    res = np.asarray(obs["residual_px"], float).reshape(-1, 2)
    n = len(res)
    if n == 0:
        return None
    uv = np.asarray(obs.get("uv_px", np.full((n, 2), np.nan)), float).reshape(-1, 2)
    if len(uv) != n:
        uv = np.full((n, 2), np.nan)

    def column(key: str, fill, dtype) -> np.ndarray:
        v = obs.get(key)
        arr = np.asarray(v, dtype=dtype).reshape(-1) if v is not None else np.array([])
        return arr if len(arr) == n else np.full(n, fill, dtype=dtype)

    return Observations(
        image=column("image", "", object),
        target=column("target", "", object),
        uv_px=uv,
        residual_px=res,
        weight=column("weight", 1.0, float),
        incidence_deg=column("incidence_deg", np.nan, float),
    )


def linear_trend(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Least-squares line ``y = slope * x + intercept`` over the finite pairs.

    Returns ``(nan, nan)`` with fewer than two distinct ``x``.
    """
    x = np.asarray(x, float).ravel()
    y = np.asarray(y, float).ravel()
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if len(x) < 2 or np.ptp(x) == 0:
        return math.nan, math.nan
    xm = x.mean()
    slope = float(np.sum((x - xm) * (y - y.mean())) / np.sum((x - xm) ** 2))
    return slope, float(y.mean() - slope * xm)


def robust_limits(values: np.ndarray, k: float = 6.0, min_half_width: float = 1e-3):
    """Plot range ``median +- k * 1.4826 * MAD`` of the finite values.

    Returns ``(lo, hi)``; ``(-1, 1)`` without finite values. The range covers
    all values when they fit within it, so clean data is never cut.
    """
    v = np.asarray(values, float).ravel()
    v = v[np.isfinite(v)]
    if len(v) == 0:
        return -1.0, 1.0
    med = float(np.median(v))
    scale = mad_sigma(v)
    if scale == 0:
        scale = float(np.std(v))
    half = max(k * scale, min_half_width)
    lo, hi = med - half, med + half
    vmin, vmax = float(v.min()), float(v.max())
    # where all values fit, shrink to them plus a small margin
    pad = 0.05 * (min(hi, vmax) - max(lo, vmin))
    lo = vmin - pad if vmin >= lo else lo
    hi = vmax + pad if vmax <= hi else hi
    if hi - lo < 2 * min_half_width:
        lo, hi = med - min_half_width, med + min_half_width
    return lo, hi


def radial_components(uv_px: np.ndarray, residual_px: np.ndarray, pp: np.ndarray):
    """Radial distance from ``pp`` and the radial / tangential residual components.

    Returns ``(r, radial, tangential)``, each (N,); the radial direction points
    away from the principal point, the tangential one is it turned +90 deg in
    image coordinates (x right, y down).
    """
    d = np.asarray(uv_px, float) - np.asarray(pp, float)
    r = np.linalg.norm(d, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        e = np.where(r[:, None] > 0, d / r[:, None], np.array([1.0, 0.0]))
    res = np.asarray(residual_px, float)
    radial = (res * e).sum(1)
    tangential = res[:, 1] * e[:, 0] - res[:, 0] * e[:, 1]
    return r, radial, tangential


def _grid(width: int, height: int, n_cols: int):
    """Cell edges (xe, ye) of a grid of about square cells over the image."""
    n_cols = max(int(n_cols), 1)
    n_rows = max(int(round(n_cols * height / max(width, 1))), 1)
    return np.linspace(0, width, n_cols + 1), np.linspace(0, height, n_rows + 1)


def binned_mean_field(uv_px, residual_px, width, height, n_cols=16, min_count=3):
    """Mean residual per grid cell.

    Returns ``(cx, cy, mean (R, C, 2), count (R, C))``: cell centres and the
    mean residual of the cells with at least ``min_count`` observations (NaN
    elsewhere).
    """
    xe, ye = _grid(width, height, n_cols)
    uv = np.asarray(uv_px, float)
    res = np.asarray(residual_px, float)
    ok = np.all(np.isfinite(uv), 1) & np.all(np.isfinite(res), 1)
    uv, res = uv[ok], res[ok]
    count, _, _ = np.histogram2d(uv[:, 1], uv[:, 0], bins=[ye, xe])
    mean = np.full(count.shape + (2,), np.nan)
    for k in range(2):
        s, _, _ = np.histogram2d(uv[:, 1], uv[:, 0], bins=[ye, xe], weights=res[:, k])
        with np.errstate(invalid="ignore", divide="ignore"):
            mean[..., k] = np.where(count >= min_count, s / count, np.nan)
    return 0.5 * (xe[1:] + xe[:-1]), 0.5 * (ye[1:] + ye[:-1]), mean, count


# --------------------------------------------------------------------------- plots


def _subplots(nrows: int = 1, ncols: int = 1, **kw):
    """A figure on its own Agg canvas (no pyplot, no global backend change)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=kw.pop("figsize", (6.4, 4.8)))
    FigureCanvasAgg(fig)
    return fig, fig.subplots(nrows, ncols, **kw)


def _save(fig, path: Path, tight: bool = False) -> Path:
    """Write ``fig``; ``tight`` crops to the drawn artists (one more draw: slower)."""
    if not tight:
        fig.tight_layout()
    fig.savefig(path, dpi=110, bbox_inches="tight" if tight else None)
    return path


def _placeholder(path: Path, title: str, message: str) -> Path:
    fig, ax = _subplots(figsize=(6, 2.5))
    ax.set_axis_off()
    ax.set_title(title)
    ax.text(0.5, 0.5, message, ha="center", va="center", fontsize=12, transform=ax.transAxes)
    return _save(fig, path)


def _fmt(v: float, digits: int = 3) -> str:
    if v is None or not np.isfinite(v):
        return "n/a"
    return f"{v:.{digits}g}" if abs(v) < 1e-3 or abs(v) >= 1e5 else f"{v:.{digits}f}"


def plot_residuals_2d(obs: Observations | None, path: Path, label: str = "") -> Path:
    """Scatter of the residuals (x, y) in px, outliers in red, RMS in the title."""
    title = f"Image residuals{label}"
    if obs is None:
        return _placeholder(path, title, "no per-observation residuals in the calibration file")
    res = obs.residual_px
    rms = float(np.sqrt(np.mean((res**2).sum(1))))
    out = obs.outlier
    rms_in = float(np.sqrt(np.mean((res[~out] ** 2).sum(1)))) if (~out).any() else math.nan
    lo_x, hi_x = robust_limits(res[:, 0])
    lo_y, hi_y = robust_limits(res[:, 1])
    half = max(abs(lo_x), abs(hi_x), abs(lo_y), abs(hi_y))
    clipped = np.clip(res, -half, half)
    outside = np.any(np.abs(res) > half, axis=1)
    fig, ax = _subplots(figsize=(6.4, 6.4))
    size = 6 if len(res) < 5000 else 2
    inl = ~out & ~outside
    ax.scatter(
        res[inl, 0],
        res[inl, 1],
        s=size,
        alpha=0.5,
        color="tab:blue",
        lw=0,
        label=f"weight >= {OUTLIER_WEIGHT} ({int((~out).sum())})",
    )
    ax.scatter(
        res[out & ~outside, 0],
        res[out & ~outside, 1],
        s=14,
        color="tab:red",
        lw=0,
        label=f"outliers, weight < {OUTLIER_WEIGHT} ({int(out.sum())})",
    )
    if outside.any():
        ax.scatter(
            clipped[outside, 0],
            clipped[outside, 1],
            s=30,
            marker="x",
            color="tab:red" if out[outside].all() else "black",
            label=f"{int(outside.sum())} beyond +-{half:.3g} px, drawn on the border",
        )
    theta = np.linspace(0, 2 * np.pi, 200)
    circle = rms_in if rms > half else rms
    what = f"RMS of weight >= {OUTLIER_WEIGHT}" if rms > half else "RMS"
    ax.plot(
        circle * np.cos(theta), circle * np.sin(theta), "k--", lw=1, label=f"{what} {circle:.3g} px"
    )
    ax.axhline(0, color="0.7", lw=0.8)
    ax.axvline(0, color="0.7", lw=0.8)
    pad = 1.03 * half
    ax.set_xlim(-pad, pad)
    ax.set_ylim(-pad, pad)
    ax.set_aspect("equal")
    ax.set_xlabel("x residual (px)")
    ax.set_ylabel("y residual (px)")
    ax.set_title(
        f"{title}\nRMS {rms:.4f} px ({rms_in:.4f} px over weight >= {OUTLIER_WEIGHT})\n"
        f"{len(res)} observations, {int(out.sum())} outliers"
    )
    ax.legend(loc="upper right", fontsize=8, framealpha=0.85)
    ax.grid(alpha=0.3)
    return _save(fig, path)


def _gauss(x, mu, sd):
    return np.exp(-0.5 * ((x - mu) / sd) ** 2) / (sd * math.sqrt(2 * math.pi))


def plot_histograms(obs: Observations | None, path: Path, label: str = "") -> Path:
    """Histograms of the x and y residuals with a Gaussian fitted to the shown range."""
    title = f"Histograms of the image residuals{label}"
    if obs is None:
        return _placeholder(path, title, "no per-observation residuals in the calibration file")
    fig, axes = _subplots(2, 1, figsize=(7.5, 7.0))
    for k, (ax, name) in enumerate(zip(axes, ("x", "y"))):
        v = obs.residual_px[:, k]
        v = v[np.isfinite(v)]
        lo, hi = robust_limits(v)
        inside = v[(v >= lo) & (v <= hi)]
        n_out = len(v) - len(inside)
        bins = int(np.clip(np.sqrt(len(inside)) * 1.5, 10, 80))
        counts, edges, _ = ax.hist(
            inside, bins=bins, range=(lo, hi), color="tab:blue", alpha=0.6, label="residuals"
        )
        mu = float(inside.mean()) if len(inside) else math.nan
        sd = float(inside.std(ddof=1)) if len(inside) > 1 else math.nan
        if np.isfinite(sd) and sd > 0:
            xs = np.linspace(lo, hi, 400)
            width = edges[1] - edges[0]
            ax.plot(
                xs,
                len(inside) * width * _gauss(xs, mu, sd),
                color="tab:red",
                lw=2,
                label=f"Gaussian fit: mean {mu:.3g} px, std {sd:.3g} px",
            )
        note = f"{n_out} of {len(v)} outside the shown range" if n_out else "all values shown"
        ax.plot([], [], " ", label=note)
        ax.set_xlim(lo, hi)
        ax.set_xlabel(f"{name} residual (px)")
        ax.set_ylabel("number of observations")
        ax.set_title(f"{name}: mean {mu:.3g} px, std {sd:.3g} px")
        ax.legend(fontsize=8, loc="upper right")
        ax.grid(alpha=0.3)
    fig.suptitle(title)
    return _save(fig, path)


def radial_trends(obs: Observations, pp: np.ndarray) -> dict[str, tuple[float, float]]:
    """Linear trends ``(slope px/px, intercept px)`` of the residual components vs radius.

    Keys ``x``, ``y``, ``radial``, ``tangential``. Fitted on the observations
    with a robust weight of at least :data:`OUTLIER_WEIGHT` (all of them if
    fewer than two are).
    """
    r, rad, tan = radial_components(obs.uv_px, obs.residual_px, pp)
    use = ~obs.outlier
    if use.sum() < 2:
        use = np.ones(len(r), bool)
    comps = {"x": obs.residual_px[:, 0], "y": obs.residual_px[:, 1], "radial": rad}
    comps["tangential"] = tan
    return {k: linear_trend(r[use], v[use]) for k, v in comps.items()}


def plot_radial(obs: Observations | None, pp: np.ndarray, path: Path, label: str = "") -> Path:
    """Residual components against radial distance, with linear trends (paper Fig. 12)."""
    title = f"Residuals vs radial distance{label}"
    if obs is None or not np.all(np.isfinite(obs.uv_px)):
        return _placeholder(path, title, "no per-observation pixels / residuals in the file")
    r, rad, tan = radial_components(obs.uv_px, obs.residual_px, pp)
    trends = radial_trends(obs, pp)
    fig, axes = _subplots(2, 1, figsize=(8, 7.5), sharex=True)
    panels = (
        (
            axes[0],
            (("x", obs.residual_px[:, 0], "tab:blue"), ("y", obs.residual_px[:, 1], "tab:orange")),
        ),
        (axes[1], (("radial", rad, "tab:green"), ("tangential", tan, "tab:purple"))),
    )
    size = 4 if len(r) < 5000 else 1.5
    xs = np.array([0.0, float(np.nanmax(r)) if len(r) else 1.0])
    n_outside = 0
    for ax, comps in panels:
        lo = min(robust_limits(v)[0] for _, v, _ in comps)
        hi = max(robust_limits(v)[1] for _, v, _ in comps)
        half = max(abs(lo), abs(hi))
        for name, v, colour in comps:
            ax.scatter(r, v, s=size, alpha=0.35, color=colour, lw=0, label=f"{name} residual")
            n_outside = max(n_outside, int(np.sum(np.abs(v) > half)))
        for name, _, colour in comps:
            slope, icpt = trends[name]
            if np.isfinite(slope):
                ax.plot(
                    xs,
                    slope * xs + icpt,
                    color=colour,
                    lw=2.2,
                    path_effects=_halo(),
                    label=f"{name} trend: slope {slope:.2e} px/px, intercept {icpt:.3g} px",
                )
        ax.axhline(0, color="0.5", lw=0.8)
        ax.set_ylim(-1.05 * half, 1.05 * half)
        ax.set_ylabel("residual (px)")
        ax.legend(fontsize=8, loc="upper left", markerscale=3, framealpha=0.85)
        ax.grid(alpha=0.3)
    axes[0].set_title("x and y components (as in Chow et al. 2018, Fig. 12)", fontsize=10)
    axes[1].set_title("radial and tangential components", fontsize=10)
    axes[1].set_xlabel("radial distance from the principal point (px)")
    ty = trends["y"]
    sub = f"y slope {ty[0]:.2e} px/px, intercept {ty[1]:.3g} px"
    if n_outside:
        sub += f"; up to {n_outside} points beyond the y range per panel"
    fig.suptitle(f"{title}\n{sub}")
    return _save(fig, path)


def _halo():
    import matplotlib.patheffects as pe

    return [pe.Stroke(linewidth=4, foreground="white"), pe.Normal()]


#: History keys of the correction loop's round number and cross-validation score.
ROUND_KEYS = ("knn_iteration", "knn_round")
CV_KEYS = ("cv_score", "cv_rmse_px")


def _first_key(rows: list[dict], keys: Sequence[str]) -> str | None:
    return next((k for k in keys if any(k in h for h in rows)), None)


def cv_curve(history) -> tuple[np.ndarray, np.ndarray, str, str] | None:
    """Cross-validation score per correction round from a history, or ``None``.

    Returns ``(x, score, x_key, score_key)``; one value per round (its last
    row) when the history has a round key, else one per row that has a score.
    """
    rows = [h for h in (history or []) if isinstance(h, dict)]
    ck = _first_key(rows, CV_KEYS)
    if ck is None:
        return None
    rows = [h for h in rows if _finite(h.get(ck))]
    if not rows:
        return None
    rk = _first_key(rows, ROUND_KEYS)
    if rk is not None and all(_finite(h.get(rk)) for h in rows):
        last = {float(h[rk]): float(h[ck]) for h in rows}
        x = np.array(sorted(last))
        return x, np.array([last[v] for v in x]), rk, ck
    x = np.array([float(h.get("iteration", k)) for k, h in enumerate(rows)])
    return x, np.array([float(h[ck]) for h in rows]), "iteration", ck


def plot_convergence(history, path: Path, label: str = "") -> Path:
    """Cost per iteration (log y), stages / rounds coloured; CV score below if present."""
    from matplotlib.ticker import MaxNLocator

    title = f"Convergence{label}"
    rows = [h for h in (history or []) if isinstance(h, dict) and "cost" in h]
    if not rows:
        return _placeholder(path, title, "no iteration history in the calibration file")
    it = np.array([float(h.get("iteration", k)) for k, h in enumerate(rows)])
    cost = np.array([float(h["cost"]) if _finite(h["cost"]) else np.nan for h in rows])
    cv = cv_curve(history)
    fig, axes = _subplots(2 if cv else 1, 1, figsize=(8, 7 if cv else 4.5))
    axes = np.atleast_1d(axes)
    ax = axes[0]
    groups = [_history_group(h) for h in rows]
    positive = np.isfinite(cost) & (cost > 0)
    if len(set(groups)) > 1:
        for g in dict.fromkeys(groups):
            m = np.array([x == g for x in groups]) & positive
            ax.plot(it[m], cost[m], "o-", ms=3, lw=1.2, label=g)
        ax.legend(fontsize=8, ncols=1 + len(set(groups)) // 8)
    else:
        ax.plot(it[positive], cost[positive], "o-", ms=3, lw=1.2, color="tab:blue")
    if positive.any():
        ax.set_yscale("log")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_xlabel("iteration")
    ax.set_ylabel("cost (weighted sum of squares / 2)")
    ax.grid(alpha=0.3, which="both")
    seconds = _total_seconds(rows)
    final = cost[np.isfinite(cost)][-1] if np.isfinite(cost).any() else math.nan
    sub = f"final cost {_fmt(final, 4)} after {int(it[-1])} iterations ({len(rows)} rows)"
    if seconds is not None:
        sub += f", {seconds:.1f} s"
    ax.set_title(f"{title}\n{sub}")
    if cv:
        x, y, xk, ck = cv
        ax2 = axes[1]
        unit = " (px)" if ck.endswith("_px") else ""
        ax2.plot(x, y, "s-", color="tab:green", ms=5)
        best = int(np.argmin(y))
        ax2.plot(x[best], y[best], "*", color="tab:red", ms=14, label=f"best {y[best]:.4g}{unit}")
        ax2.legend(fontsize=8)
        ax2.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax2.set_xlabel("kNN correction round" if xk in ROUND_KEYS else "iteration")
        what = "RMSE" if "rmse" in ck else "score"
        ax2.set_ylabel(f"cross-validation {what}{unit}")
        ax2.set_title(f"Cross-validation {what} of the learned correction ({ck})", fontsize=10)
        ax2.grid(alpha=0.3)
    return _save(fig, path)


def _total_seconds(rows: list[dict]) -> float | None:
    """Wall time of a history whose ``seconds`` count up within each run and restart."""
    s = [float(h["seconds"]) for h in rows if _finite(h.get("seconds"))]
    if not s:
        return None
    total = 0.0
    for a, b in zip(s, s[1:]):
        if b < a:
            total += a
    return total + s[-1]


def _history_group(h: dict) -> str:
    """Legend label of a history row: its kNN round and / or its stage."""
    parts = []
    for k in ROUND_KEYS:
        if h.get(k) is not None:
            parts.append(f"kNN round {h[k]}")
            break
    if h.get("stage") is not None:
        parts.append(f"stage {h['stage']}")
    return ", ".join(parts) or "adjustment"


def _finite(v) -> bool:
    try:
        return v is not None and math.isfinite(float(v))
    except (TypeError, ValueError):
        return False


def _frame(ax, width: int, height: int) -> None:
    from matplotlib.patches import Rectangle

    ax.add_patch(Rectangle((0, 0), width, height, fill=False, ec="black", lw=1.5, zorder=5))
    m = 0.03 * max(width, height)
    ax.set_xlim(-m, width + m)
    ax.set_ylim(height + m, -m)  # image convention: y down
    ax.set_aspect("equal")
    ax.set_xlabel("u (px)")
    ax.set_ylabel("v (px)")


def incidence_90_curve(camera) -> np.ndarray | None:
    """Pixels (K, 2) of the rays at 90 deg incidence that fall inside the image, or ``None``.

    The curve is drawn through the model (Brown terms and learned correction
    included); for the plain sphere model it is the circle of radius ``c``
    around the principal point.
    """
    phi = np.linspace(0, 2 * np.pi, 721)
    rays = np.column_stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)])
    try:
        uv = np.asarray(camera.project(rays), float)
    except Exception:  # a correction that cannot be inverted: use the plain sphere
        uv = np.column_stack([camera.xp + camera.c * rays[:, 0], camera.yp + camera.c * rays[:, 1]])
    inside = (
        np.all(np.isfinite(uv), 1)
        & (uv[:, 0] >= 0)
        & (uv[:, 0] <= camera.width)
        & (uv[:, 1] >= 0)
        & (uv[:, 1] <= camera.height)
    )
    return uv if inside.any() else None


def correction_field(camera, uv_obs: np.ndarray | None, n_cols: int = 20):
    """The model's measurement correction ``camera.distortion_px`` on a grid.

    Only cells holding observations or next to one are kept (a learned
    correction means nothing far from the data). Returns ``(xy (K, 2),
    delta (K, 2), note)``; ``xy`` is empty with ``note`` saying why when there
    is nothing to draw.
    """
    if not camera.brown and camera.correction is None:
        return np.zeros((0, 2)), np.zeros((0, 2)), "the model has no measurement correction"
    xe, ye = _grid(camera.width, camera.height, n_cols)
    cx, cy = 0.5 * (xe[1:] + xe[:-1]), 0.5 * (ye[1:] + ye[:-1])
    gx, gy = np.meshgrid(cx, cy)
    keep = np.ones(gx.shape, bool)
    if uv_obs is not None and len(uv_obs) and np.all(np.isfinite(uv_obs)):
        count, _, _ = np.histogram2d(uv_obs[:, 1], uv_obs[:, 0], bins=[ye, xe])
        occ = count > 0
        dil = occ.copy()
        dil[1:] |= occ[:-1]
        dil[:-1] |= occ[1:]
        dil[:, 1:] |= occ[:, :-1]
        dil[:, :-1] |= occ[:, 1:]
        keep = dil
    xy = np.column_stack([gx[keep], gy[keep]])
    try:
        delta = np.asarray(camera.distortion_px(xy), float).reshape(-1, 2)
    except Exception as exc:  # report, do not fail, on a correction that cannot evaluate
        return np.zeros((0, 2)), np.zeros((0, 2)), f"correction could not be evaluated ({exc})"
    ok = np.all(np.isfinite(delta), 1)
    xy, delta = xy[ok], delta[ok]
    if len(delta) == 0 or float(np.max(np.linalg.norm(delta, axis=1))) < 1e-9:
        return np.zeros((0, 2)), np.zeros((0, 2)), "the correction is zero over the image"
    return xy, delta, ""


def _quiver(ax, xy, vec, cell: float, colour="tab:red", label_prefix=""):
    """Quiver in image coordinates, the longest arrow ~0.9 cell; returns the magnification."""
    mag = np.linalg.norm(vec, axis=1)
    vmax = float(np.nanmax(mag))
    scale = vmax / (0.9 * cell)  # data units per px of arrow
    q = ax.quiver(
        xy[:, 0],
        xy[:, 1],
        vec[:, 0],
        vec[:, 1],
        mag,
        angles="xy",
        scale_units="xy",
        scale=scale,
        cmap="plasma",
        width=0.004,
        zorder=4,
    )
    ref = float(f"{vmax:.1g}")
    if ref <= 0:
        ref = vmax
    ax.quiverkey(
        q,
        1.0,
        -0.1,
        ref,
        f"{label_prefix}{ref:g} px (arrows x{1 / scale:.3g})",
        labelpos="W",
        coordinates="axes",
        fontproperties={"size": 8},
    )
    return q, 1 / scale


def plot_coverage(calib: Calibration, obs: Observations | None, path: Path, label="") -> Path:
    """Image frame with observations, principal point, 90 deg curve and correction field."""
    cam = calib.camera
    fig, ax = _subplots(figsize=(9, 9 * cam.height / max(cam.width, 1) + 1.2))
    uv = obs.uv_px if obs is not None else None
    n_obs = 0
    if uv is not None and np.all(np.isfinite(uv)):
        n_obs = len(uv)
        ax.scatter(uv[:, 0], uv[:, 1], s=1.5, color="0.45", lw=0)
        ax.plot([], [], ".", color="0.45", ms=5, label=f"observations ({n_obs})")
    ax.plot(cam.xp, cam.yp, "+", color="tab:blue", ms=14, mew=2.5, label="principal point")
    curve = incidence_90_curve(cam)
    if curve is not None:
        ax.plot(curve[:, 0], curve[:, 1], "--", color="tab:green", lw=1.5, label="90 deg incidence")
    xy, delta, note = correction_field(cam, uv)
    cell = max(cam.width, cam.height) / 20
    if len(xy):
        q, gain = _quiver(ax, xy, delta, cell, label_prefix="correction ")
        cb = fig.colorbar(q, ax=ax, shrink=0.7, pad=0.02)
        cb.set_label("correction magnitude (px)")
        mag = np.linalg.norm(delta, axis=1)
        corr = f"correction up to {mag.max():.3g} px (median {np.median(mag):.3g} px)"
    else:
        corr = note
    _frame(ax, cam.width, cam.height)
    ax.set_title(
        f"Image coverage{label}: {cam.width} x {cam.height} px, pp ({cam.xp:.1f}, {cam.yp:.1f}) px,"
        f" c {cam.c:.1f} px\n{corr}",
        fontsize=10,
    )
    ax.legend(loc="lower left", fontsize=8, framealpha=0.85)
    return _save(fig, path, tight=True)


def target_shifts_of(calib: Calibration) -> tuple[np.ndarray, np.ndarray] | None:
    """Nominal coordinates (K, 3) and adjusted-minus-nominal shifts (K, 3) of the targets
    that had a sigma, in the calibration's units; None when the file has none."""
    ts = calib.extra.get("target_shifts") or {}
    try:
        nominal = np.asarray(ts.get("nominal_xyz", []), float).reshape(-1, 3)
        shift = np.asarray(ts.get("shift", []), float).reshape(-1, 3)
    except (TypeError, ValueError):
        return None
    if len(nominal) == 0 or nominal.shape != shift.shape:
        return None
    return nominal, shift


def plot_target_shifts(calib: Calibration, path: Path, label: str = "") -> Path | None:
    """Where the adjustment moved the targets that had a sigma (a board's real shape).

    For a planar target set (a board) the nominal positions are drawn in the board's
    plane, the in-plane shifts as arrows and the out-of-plane shift as colour; for a
    3D set, the shift of each target against its distance from the centroid. Returns
    None when the calibration has no such targets.
    """
    got = target_shifts_of(calib)
    if got is None:
        return None
    nominal, shift = got
    milli = 1000.0 if calib.units == "m" else 1.0
    unit = "mm" if calib.units == "m" else calib.units
    centre = nominal.mean(axis=0)
    _, sv, vt = np.linalg.svd(nominal - centre, full_matrices=False)
    planar = len(nominal) >= 3 and sv[-1] <= 1e-6 * max(sv[0], 1e-300)
    fig, ax = _subplots(figsize=(8, 6))
    norm = np.linalg.norm(shift, axis=1) * milli
    if planar:
        e1, e2, n = vt[0], vt[1], vt[2]
        xy = (nominal - centre) @ np.stack([e1, e2], axis=1) * milli
        d_in = shift @ np.stack([e1, e2], axis=1) * milli
        d_out = shift @ n * milli
        lim = max(float(np.max(np.abs(d_out))), 1e-12)
        sc = ax.scatter(xy[:, 0], xy[:, 1], c=d_out, cmap="coolwarm", vmin=-lim, vmax=lim, s=60)
        cb = fig.colorbar(sc, ax=ax, shrink=0.8)
        cb.set_label(f"out-of-plane shift ({unit})")
        extent = float(np.ptp(xy, axis=0).max()) or 1.0
        gain = 0.05 * extent / max(float(np.max(np.linalg.norm(d_in, axis=1))), 1e-12)
        ax.quiver(
            xy[:, 0],
            xy[:, 1],
            d_in[:, 0] * gain,
            d_in[:, 1] * gain,
            angles="xy",
            scale_units="xy",
            scale=1,
            width=0.004,
        )
        ax.set_aspect("equal")
        ax.set_xlabel(f"along the target plane ({unit})")
        ax.set_ylabel(f"across ({unit})")
        what = f"in-plane arrows x{gain:.3g}"
    else:
        dist = np.linalg.norm(nominal - centre, axis=1) * milli
        ax.scatter(dist, norm, s=12)
        ax.set_xlabel(f"distance from the targets' centroid ({unit})")
        ax.set_ylabel(f"shift ({unit})")
        what = "3D control"
    rms = float(np.sqrt(np.mean(norm**2)))
    ax.set_title(
        f"Targets moved by the adjustment{label}: {len(norm)} targets, RMS {rms:.3g} {unit}, "
        f"max {norm.max():.3g} {unit}\n({what}; adjusted minus nominal coordinates)",
        fontsize=10,
    )
    return _save(fig, path)


def plot_residual_field(
    calib: Calibration, obs: Observations | None, path: Path, label: str = "", n_cols: int = 16
) -> Path:
    """Mean residual per grid cell as a quiver over the image: the systematic error left."""
    title = f"Mean residual per cell{label}"
    if obs is None or not np.all(np.isfinite(obs.uv_px)):
        return _placeholder(path, title, "no per-observation pixels / residuals in the file")
    cam = calib.camera
    use = ~obs.outlier
    cx, cy, mean, count = binned_mean_field(
        obs.uv_px[use], obs.residual_px[use], cam.width, cam.height, n_cols
    )
    gx, gy = np.meshgrid(cx, cy)
    ok = np.all(np.isfinite(mean), -1)
    fig, ax = _subplots(figsize=(9, 9 * cam.height / max(cam.width, 1) + 1.2))
    ax.plot(cam.xp, cam.yp, "+", color="tab:blue", ms=14, mew=2.5, label="principal point")
    if ok.any():
        xy = np.column_stack([gx[ok], gy[ok]])
        vec = mean[ok]
        mag = np.linalg.norm(vec, axis=1)
        if mag.max() > 0:
            q, _ = _quiver(ax, xy, vec, cam.width / n_cols, label_prefix="mean residual ")
            cb = fig.colorbar(q, ax=ax, shrink=0.7, pad=0.02)
            cb.set_label("mean residual magnitude (px)")
        sub = (
            f"{int(ok.sum())} cells with >= 3 observations; largest cell mean {mag.max():.3g} px, "
            f"median {np.median(mag):.3g} px"
        )
    else:
        sub = "no cell holds 3 observations"
    _frame(ax, cam.width, cam.height)
    ax.set_title(f"{title} (outliers excluded)\n{sub}", fontsize=10)
    ax.legend(loc="lower left", fontsize=8)
    return _save(fig, path, tight=True)


def uncertainty_of(calib: Calibration):
    """The projection uncertainty map of ``calib`` and a note, or ``(None, why)``.

    The map is :func:`~gtsam_sphere.analysis.uncertainty.uncertainty_map_of`'s
    default: points at infinity, the camera rotation compensated over the
    calibration's observations (its ``sigma_fixed_ray_px`` holds the
    uncompensated term for comparison).

    Returns
    -------
    umap : UncertaintyMap or None
    note : str
        Where the covariance came from, or why there is no map.
    """
    from ..analysis.uncertainty import uncertainty_map_of
    from ..io.dataset import DatasetError

    try:
        umap = uncertainty_map_of(calib)
    except DatasetError as exc:
        return None, str(exc).split(": ", 1)[-1]
    except Exception as exc:  # report, do not fail, on a camera that cannot be propagated
        return None, f"could not be computed ({exc})"
    return umap, umap.note


def plot_uncertainty(
    calib: Calibration, obs: Observations | None, umap, note: str, path: Path, label: str = ""
) -> Path:
    """Map of the projection uncertainty (px) over the image frame, observations on top."""
    title = f"Projection uncertainty{label}"
    if umap is None:
        return _placeholder(path, title, f"no map: {note}")
    cam = calib.camera
    fig, ax = _subplots(figsize=(9, 9 * cam.height / max(cam.width, 1) + 1.2))
    du = umap.u_px[1] - umap.u_px[0] if len(umap.u_px) > 1 else cam.width
    dv = umap.v_px[1] - umap.v_px[0] if len(umap.v_px) > 1 else cam.height
    extent = (
        umap.u_px[0] - du / 2,
        umap.u_px[-1] + du / 2,
        umap.v_px[-1] + dv / 2,
        umap.v_px[0] - dv / 2,
    )
    vals = umap.sigma_px
    finite = vals[np.isfinite(vals)]
    vmax = float(np.percentile(finite, 99)) if len(finite) else 1.0
    im = ax.imshow(
        np.ma.masked_invalid(vals),
        extent=extent,
        origin="upper",
        cmap="viridis",
        vmin=0.0,
        vmax=vmax if vmax > 0 else 1.0,
        interpolation="nearest",
        zorder=1,
    )
    cb = fig.colorbar(im, ax=ax, shrink=0.7, pad=0.02)
    cb.set_label("projection standard deviation (px)")
    uv = obs.uv_px if obs is not None else None
    inside = None
    if uv is not None and len(uv) and np.all(np.isfinite(uv)):
        ax.scatter(uv[:, 0], uv[:, 1], s=1.0, color="white", alpha=0.5, lw=0, zorder=2)
        ax.plot([], [], ".", color="0.6", ms=5, label=f"observations ({len(uv)})")
        inside = _observed_cells(umap, uv)
    ax.plot(cam.xp, cam.yp, "+", color="tab:red", ms=14, mew=2.5, label="principal point")
    _frame(ax, cam.width, cam.height)
    summ = umap.summary()
    sub = f"median {_fmt(summ['median_px'])} px, max {_fmt(summ['max_px'])} px over the image"
    if inside is not None:
        s_in = umap.summary(inside)
        sub += f"; median {_fmt(s_in['median_px'])} px where observed"
    which = _uncertainty_which(umap)
    ax.set_title(f"{title}\n{sub}\n{which}\n{note}", fontsize=9)
    ax.legend(loc="lower left", fontsize=8, framealpha=0.85)
    return _save(fig, path, tight=True)


def _uncertainty_which(umap) -> str:
    """Which map is shown, and the fixed-ray figure for comparison, in one line."""
    if getattr(umap, "compensation", "none") == "none":
        return "shown: a fixed camera-frame ray (camera frame not compensated)"
    text = "shown: camera rotation compensated"
    if umap.compensation != "rotation":
        text = "shown: camera rotation and translation compensated"
    fixed = _fixed_ray_total(umap)
    if fixed is not None and np.any(np.isfinite(fixed)):
        text += f" (a fixed camera-frame ray: median {_fmt(float(np.nanmedian(fixed)))} px)"
    return text


def _fixed_ray_total(umap):
    """The map's total (px, kNN term included) for a fixed camera-frame ray, or ``None``."""
    fixed = getattr(umap, "sigma_fixed_ray_px", None)
    if fixed is None:
        return None
    return np.sqrt(fixed**2 + umap.sigma_knn_px**2)


def _observed_cells(umap, uv: np.ndarray) -> np.ndarray:
    """Cells (R, C) of an uncertainty map holding at least one observation."""
    du = umap.u_px[1] - umap.u_px[0] if len(umap.u_px) > 1 else np.inf
    dv = umap.v_px[1] - umap.v_px[0] if len(umap.v_px) > 1 else np.inf
    ci = np.clip(np.floor((uv[:, 0] - umap.u_px[0]) / du + 0.5).astype(int), 0, len(umap.u_px) - 1)
    ri = np.clip(np.floor((uv[:, 1] - umap.v_px[0]) / dv + 0.5).astype(int), 0, len(umap.v_px) - 1)
    mask = np.zeros(umap.sigma_px.shape, bool)
    mask[ri, ci] = True
    return mask


# --------------------------------------------------------------------------- page


@dataclass
class _Table:
    header: list[str]
    rows: list[list[str]]


@dataclass
class _Image:
    src: str
    caption: str


def _length(v: float, units: str) -> str:
    """A length in the dataset's units, metres shown in millimetres."""
    return f"{v * 1000:g} mm" if units == "m" else f"{v:g} {units}"


def _value(v) -> str:
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        v = float(v)
        if not math.isfinite(v):
            return str(v)
        if v != 0 and (abs(v) < 1e-3 or abs(v) >= 1e6):
            return f"{v:.4e}"
        return f"{v:.4f}"
    return str(v)


def _sigma_of(sigmas: dict, name: str):
    for key in (name, f"{name}_px", name.removesuffix("_px")):
        if key in sigmas:
            return sigmas[key]
    return None


def _intrinsics_table(calib: Calibration) -> _Table:
    cam = calib.camera
    sig = calib.statistics.get("intrinsics_sigma") or {}
    rows = [
        ["xp", _value(cam.xp), "px"],
        ["yp", _value(cam.yp), "px"],
        ["c", _value(cam.c), "px"],
    ]
    rows += [[k, _value(v), ""] for k, v in cam.brown.items()]
    if cam.brown:
        rows.append(["brown_scale_px", _value(cam.brown_scale_px), "px"])
    header = ["parameter", "value", "unit"]
    if sig:
        header.insert(2, "sigma")
        for row in rows:
            s = _sigma_of(sig, row[0])
            row.insert(2, _value(s) if s is not None else "")
    return _Table(header, rows)


def _statistics_table(stats: dict) -> _Table:
    rows = [[d, f"`{k}`", _value(stats[k])] for k, d in _STAT_ROWS if k in stats]
    known = {k for k, _ in _STAT_ROWS} | {"intrinsics_sigma"}
    rows += [
        ["", f"`{k}`", _value(v)]
        for k, v in stats.items()
        if k not in known and isinstance(v, (int, float, str, bool, np.number))
    ]
    return _Table(["quantity", "key", "value"], rows)


def _downweighted_table(calib: Calibration, n: int = TOP_DOWNWEIGHTED) -> tuple[_Table, int]:
    rows = []
    for d in calib.extra.get("downweighted") or []:
        r = np.asarray(d.get("residual_px", [np.nan, np.nan]), float).reshape(-1)[:2]
        rows.append((float(np.hypot(*r)), d, r))
    rows.sort(key=lambda t: -t[0] if math.isfinite(t[0]) else 0.0)
    table = _Table(
        ["#", "image", "target", "x res. (px)", "y res. (px)", "norm (px)", "weight", "outlier"],
        [
            [
                str(k + 1),
                str(d.get("image", "")),
                str(d.get("target", "")),
                f"{r[0]:.3f}",
                f"{r[1]:.3f}",
                f"{norm:.3f}",
                f"{float(d.get('weight', math.nan)):.3f}",
                "yes" if d.get("outlier") else "no",
            ]
            for k, (norm, d, r) in enumerate(rows[:n])
        ],
    )
    return table, len(rows)


def _label_of(c, k: int) -> str:
    """Column label of a compared calibration: its file, else its dataset, else its index."""
    if isinstance(c, Calibration):
        src = c.extra.get("source")
        return f"{Path(str(src)).stem if src else f'#{k}'} ({c.model})"
    p = Path(c)
    return "/".join(p.parts[-2:])


def _unique(labels: list[str]) -> list[str]:
    return [f"{x} #{k}" if labels.count(x) > 1 else x for k, x in enumerate(labels)]


def _comparison_table(calibs: Sequence[Calibration], labels: Sequence[str]) -> _Table:
    keys = [
        "rms_px",
        "rms_px_without_outliers",
        "n_observations",
        "n_rejected",
        "n_downweighted",
        "n_outliers",
        "sigma_px",
        "cost",
        "redundancy",
        "variance_factor",
        "max_incidence_deg",
        "iterations",
        "converged",
    ]
    header = ["quantity", *labels]
    rows = [
        ["c (px)"] + [_value(c.camera.c) for c in calibs],
        ["xp (px)"] + [_value(c.camera.xp) for c in calibs],
        ["yp (px)"] + [_value(c.camera.yp) for c in calibs],
    ]
    for key in keys:
        if any(key in c.statistics for c in calibs):
            rows.append([f"`{key}`"] + [_value(c.statistics.get(key, "")) for c in calibs])
    return _Table(header, rows)


def _md_cell(s: str) -> str:
    return str(s).replace("|", "\\|").replace("\n", " ")


def _markdown(blocks) -> str:
    out = []
    for b in blocks:
        if isinstance(b, _Table):
            out.append("| " + " | ".join(_md_cell(h) for h in b.header) + " |")
            out.append("|" + "|".join("---" for _ in b.header) + "|")
            out += ["| " + " | ".join(_md_cell(c) for c in row) + " |" for row in b.rows]
            out.append("")
        elif isinstance(b, _Image):
            out += [f"![{b.caption}]({b.src})", "", f"*{b.caption}*", ""]
        elif isinstance(b, tuple):  # (level, heading)
            out += ["#" * b[0] + " " + b[1], ""]
        else:
            out += [str(b), ""]
    return "\n".join(out)


_LINK = re.compile(r"\[([^\]]+)\]\(([^)\s]+)\)")
_BOLD = re.compile(r"\*\*(.+?)\*\*")


def _inline_html(text: str) -> str:
    """Escape ``text`` and turn Markdown ``code`` spans, ``[links](href)`` and ``**bold**``
    into HTML."""
    parts = html.escape(text).split("`")
    out = []
    for k, p in enumerate(parts):
        if k % 2:
            out.append(f"<code>{p}</code>")
        else:
            p = _LINK.sub(r'<a href="\2">\1</a>', p)
            out.append(_BOLD.sub(r"<strong>\1</strong>", p))
    return "".join(out)


def _html(blocks, title: str) -> str:
    body = []
    for b in blocks:
        if isinstance(b, _Table):
            head = "".join(f"<th>{_inline_html(h)}</th>" for h in b.header)
            rows = "".join(
                "<tr>" + "".join(f"<td>{_inline_html(c)}</td>" for c in row) + "</tr>"
                for row in b.rows
            )
            body.append(f"<table><thead><tr>{head}</tr></thead><tbody>{rows}</tbody></table>")
        elif isinstance(b, _Image):
            cap = html.escape(b.caption)
            body.append(
                f'<figure><img src="{html.escape(b.src)}" alt="{cap}">'
                f"<figcaption>{cap}</figcaption></figure>"
            )
        elif isinstance(b, tuple):
            body.append(f"<h{b[0]}>{_inline_html(b[1])}</h{b[0]}>")
        else:
            body.append(f"<p>{_inline_html(str(b))}</p>")
    style = (
        "body{font-family:sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;color:#222}"
        "table{border-collapse:collapse;margin:0.5em 0 1.5em}"
        "th,td{border:1px solid #bbb;padding:3px 8px;text-align:left}"
        "th{background:#eee}img{max-width:100%;border:1px solid #ddd}"
        "figure{margin:1em 0 2em}figcaption{font-style:italic;color:#555}"
        "code{background:#f3f3f3;padding:0 3px}"
    )
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f"<title>{html.escape(title)}</title><style>{style}</style></head>\n<body>\n"
        + "\n".join(body)
        + "\n</body></html>\n"
    )


def _load(c) -> Calibration | RigCalibration:
    if isinstance(c, (Calibration, RigCalibration)):
        return c
    return load_calibration(c)


def write_report(
    calibration_path_or_obj: str | os.PathLike | Calibration,
    out_dir: str | os.PathLike,
    *,
    compare_with: Sequence[Calibration | str | os.PathLike] | None = None,
    title: str | None = None,
) -> dict[str, Path]:
    """Write the plots, ``report.md`` and ``index.html`` of one calibration.

    Parameters
    ----------
    calibration_path_or_obj : path or Calibration
        A ``gtsam-sphere/calibration@1`` file or a loaded calibration; a
        ``calibration@2`` rig writes the rig page and one page per camera
        (:func:`gtsam_sphere.apps.report_rig.write_rig_report`, whose paths are
        returned).
    out_dir : path
        Created if needed; existing report files in it are overwritten.
    compare_with : list of Calibration (or paths), optional
        Adds a table comparing their statistics with this calibration's.
    title : str, optional
        Page title (default: ``"Calibration report: <file or model>"``).

    Returns
    -------
    dict
        ``{"residuals_2d": Path, "histograms": ..., "radial": ..., "convergence": ...,
        "coverage": ..., "residual_field": ..., "uncertainty": ..., "markdown": report.md,
        "html": index.html}``.

    Raises
    ------
    DatasetError
        If the file cannot be read as a calibration.
    """
    source = None if isinstance(calibration_path_or_obj, Calibration) else calibration_path_or_obj
    calib = _load(calibration_path_or_obj)
    if isinstance(calib, RigCalibration):  # calibration@2: report_rig.write_any_report
        from ..core.errors import OptionsError

        raise OptionsError(
            f"{source or 'the calibration'} is a rig (calibration@2): its report is "
            "report_rig.write_rig_report (or report_rig.write_any_report for either kind)"
        )
    others = [_load(c) for c in compare_with or []]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    cam = calib.camera
    obs = observations_of(calib)
    stats = calib.statistics
    history = calib.extra.get("history") or []

    paths: dict[str, Path] = {}
    paths["residuals_2d"] = plot_residuals_2d(obs, out / "residuals_2d.png")
    paths["histograms"] = plot_histograms(obs, out / "histograms.png")
    paths["radial"] = plot_radial(obs, cam.principal_point_px, out / "radial.png")
    paths["convergence"] = plot_convergence(history, out / "convergence.png")
    paths["coverage"] = plot_coverage(calib, obs, out / "coverage.png")
    paths["residual_field"] = plot_residual_field(calib, obs, out / "residual_field.png")
    shifts_png = plot_target_shifts(calib, out / "target_shifts.png")
    if shifts_png is not None:
        paths["target_shifts"] = shifts_png
    umap, unote = uncertainty_of(calib)
    paths["uncertainty"] = plot_uncertainty(calib, obs, umap, unote, out / "uncertainty.png")

    name = Path(str(source)).name if source is not None else calib.model
    title = title or f"Calibration report: {name}"
    blocks: list = [(1, title)]
    intro = f"Model `{calib.model}`, image {cam.width} x {cam.height} px, units {calib.units}"
    if source is not None:
        intro += f", file `{source}`"
    elif calib.extra.get("source"):
        intro += f", dataset `{calib.extra['source']}`"
    blocks.append(intro + ".")
    summary = []
    if "rms_px" in stats:
        summary.append(f"RMS {_value(stats['rms_px'])} px")
    elif obs is not None:
        rms = float(np.sqrt(np.mean((obs.residual_px**2).sum(1))))
        summary.append(f"RMS {_value(rms)} px (from the stored residuals)")
    if "n_observations" in stats:
        summary.append(f"{stats['n_observations']} observations")
    if "variance_factor" in stats:
        summary.append(f"variance factor {_value(stats['variance_factor'])}")
    if "converged" in stats:
        summary.append("converged" if stats["converged"] else "**did not converge**")
    if summary:
        blocks.append("Summary: " + ", ".join(summary) + ".")

    blocks += [(2, "Camera model"), _intrinsics_table(calib)]
    if cam.correction is not None:
        blocks.append(f"Learned correction: `{type(cam.correction).__name__}`.")
    if obs is not None:
        tr = radial_trends(obs, cam.principal_point_px)
        blocks += [
            (2, "Radial trend of the residuals"),
            _Table(
                ["component", "slope (px/px)", "intercept (px)"],
                [[k, f"{s:.3e}", f"{i:.4f}"] for k, (s, i) in tr.items()],
            ),
        ]
    blocks += [(2, "Statistics"), _statistics_table(stats)]
    if "target_shifts" in paths:
        sigma = stats.get("control_sigma")
        why = (
            f"The board's corners were estimated around their nominal coordinates with a "
            f"sigma of {_length(sigma, calib.units)} (`--control-sigma`)"
            if sigma is not None
            else "These targets had a sigma in the dataset"
        )
        blocks += [
            (2, "Target shape"),
            why + ": the figure shows where the images put them. A smooth pattern (a bowl, "
            "a stretch along one axis) is the real shape of the board; shifts of a few "
            "tenths of a millimetre are common for printed boards and, ignored, end up in "
            "the residuals and the lens.",
            _Image("target_shifts.png", "Targets moved by the adjustment (the board's shape)"),
        ]
    if others:
        inputs = [calibration_path_or_obj, *compare_with]
        labels = _unique([_label_of(c, k) for k, c in enumerate(inputs)])
        models = [
            f"{lb} (`{c.model}`)" if "(" not in lb else lb
            for lb, c in zip(labels, [calib, *others])
        ]
        blocks += [(2, "Comparison"), _comparison_table([calib, *others], models)]
    table, n_down = _downweighted_table(calib)
    blocks.append((2, "Down-weighted observations"))
    if n_down:
        shown = min(n_down, TOP_DOWNWEIGHTED)
        blocks += [f"{n_down} observations have a robust weight below 1; the {shown} largest:"]
        blocks.append(table)
    else:
        blocks.append("None: every observation has full weight (or none were recorded).")
    blocks.append((2, "Projection uncertainty"))
    blocks.append(
        "How to read it: each cell is the standard deviation, in pixels, of where a ray at "
        "infinity would land in the image if the intrinsics were drawn from their estimated "
        "covariance (and, with a kNN correction, the standard error of its local average). "
        "The camera frame is only known through the calibration's poses, so each draw is "
        "first re-aligned by the camera rotation that best matches the nominal image over the "
        "observations (weighted by their number): an error the poses absorb, such as most of "
        "the principal point's, moves no image of the world and is not counted. Where the map "
        "is small next to the residual RMS the calibration pins the image down; where it grows "
        "(usually away from the observations) the model is extrapolating."
    )
    if umap is not None:
        summ = umap.summary()
        text = (
            f"Shown: {umap.describe()}. Median {_value(summ['median_px'])} px, max "
            f"{_value(summ['max_px'])} px over {summ['n_cells']} cells"
        )
        if obs is not None and np.all(np.isfinite(obs.uv_px)):
            s_in = umap.summary(_observed_cells(umap, obs.uv_px))
            text += f" ({_value(s_in['median_px'])} px median where observed)"
        fixed = _fixed_ray_total(umap)
        if umap.compensation != "none" and fixed is not None:
            ok = np.isfinite(fixed)
            if ok.any():
                text += (
                    f"; for a fixed camera-frame ray (no compensation, "
                    f"`uncertainty_map_of(..., compensate_rotation=False)`) median "
                    f"{_value(float(np.median(fixed[ok])))} px, max "
                    f"{_value(float(np.max(fixed[ok])))} px"
                )
        if umap.motion_sigma is not None and len(umap.motion_sigma) >= 3:
            mrad = ", ".join(f"{1e3 * x:.3g}" for x in umap.motion_sigma[:3])
            text += f"; the fitted rotation's sigma (x, y, z) is {mrad} mrad"
        blocks.append(text + f". Source: {umap.note}.")
    else:
        blocks.append(f"No map: {unote}.")
    blocks.append(_Image(paths["uncertainty"].name, PLOTS["uncertainty"]))
    blocks.append((2, "Plots"))
    for key, caption in PLOTS.items():
        if key != "uncertainty":
            blocks.append(_Image(paths[key].name, caption))

    paths["markdown"] = out / "report.md"
    paths["markdown"].write_text(_markdown(blocks), encoding="utf-8")
    paths["html"] = out / "index.html"
    paths["html"].write_text(_html(blocks, title), encoding="utf-8")
    return paths


# --------------------------------------------------------------------------- CLI


def add_cli_arguments(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``gtsam-sphere report``."""
    parser.add_argument(
        "calibration",
        help="gtsam-sphere/calibration@1 file, or @2 (rig: a rig page and a page per camera)",
    )
    parser.add_argument("-o", "--output", required=True, help="directory to write the report to")
    parser.add_argument(
        "--compare",
        nargs="+",
        default=[],
        metavar="CALIB",
        help="other calibration files whose statistics to compare in a table",
    )
    parser.add_argument("--title", default=None, help="page title")


def run_cli(args) -> int:
    """Run ``gtsam-sphere report`` on a single-camera calibration; 0 on success (bad input
    raises ``DatasetError``; a rig: :func:`gtsam_sphere.apps.report_rig.run_cli`)."""
    paths = write_report(
        args.calibration, args.output, compare_with=list(args.compare), title=args.title
    )
    print(f"wrote {paths['html']} and {paths['markdown']} with {len(PLOTS)} plots")
    return 0
