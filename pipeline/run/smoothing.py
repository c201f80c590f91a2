"""Temporal smoothing of a session's centrelines: less jitter, no blur, outliers ignored.

Each centreline point (same index = same arc-length fraction along the curve) is
smoothed over time by a cubic smoothing spline (``scipy.interpolate.
make_smoothing_spline``) through the session's good frames, on their real
timestamps. Its one parameter, the smoothing weight, is chosen from the data by
cross-validation over the whole session (whose splines are solved in Reinsch's
form, :func:`_spline_predictions`): slow, noisy motion gets a stiff spline,
fast motion a supple one, and noise-free motion is left alone. One weight serves
the whole session: a recording that alternates very slow and very fast motion
gets a compromise between the two.

The cross-validation predicts each held-out frame from frames at least three
frames away (h-block cross-validation; Burman, Chow & Nolan 1994). The
reconstruction's errors are alike in neighbouring frames (lag-1 autocorrelation
~0.5 at the tip), so a spline through a held-out frame's immediate neighbours
predicts its error too: the even/odd split used before chose splines that
followed the error, leaving 7.9x the truth's tip jitter on a nearly still
straight tube and 1.9x on a thick loop. The fitted frames stay dense (three in
every eight) so that fast motion is sampled well enough to be predicted, not
aliased. Where the errors stay alike for longer than the gap, the best weight
still follows them; so the weight is then stiffened for as long as the data
cannot tell the stiffer spline apart (a paired one-standard-error rule). On 19
synthetic sessions of 150-900 frames (every shape, both rigs, radii 4-9 mm) the
smoothed tip jitter is 0.92-1.43x the truth's (0.92-3.0x without the
stiffening, 1.0-7.9x with the even/odd split), and on the 900-frame demo the
mean centreline error drops from 0.103 to 0.077 mm.

A plain least-squares fit would spread one badly reconstructed frame over its ten
neighbours. So wrong frames are found first and left out: in a wider window
(+-8 frames, so that a few wrong frames in a row still leave enough good ones), a
frame is an outlier when its deviation from the fit (the RMS over its points)
exceeds six times the median deviation (LOWESS's cut-off, Cleveland 1979), kept
between ``min_outlier_mm`` and ``max_outlier_mm``, and is the largest in its window
(its neighbours deviate only because of it). Outliers are removed one per window
at a time, refitting in between, until none is left. An outlier's smoothed curve
is then the fit of its neighbours alone. Where most frames are wrong (a pose the
reconstruction fails on for a while), too few are left to fit and the frames
stay as reconstructed: smoothing does no harm there.

Failed frames (NaN rows) stay NaN and are simply absent from their neighbours'
fits. Where a fit would amplify noise instead of reducing it (the first and last
frames, or beside long gaps, where the window is one-sided), the frame is left
as reconstructed.

Smoothing runs after the last frame (``[centerline] smooth`` in session.toml, on
by default: on the synthetic shapes it lowered the mean, p95, tip error and tip
jitter wherever the per-frame curves were mostly right, and changed nothing
measurable where they were mostly wrong). The smoothed curves are logged beside
the per-frame ones, never instead of them.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.interpolate import make_smoothing_spline
from scipy.linalg import solveh_banded

FloatArray = NDArray[np.float64]

# LOWESS's choice (Cleveland 1979): outliers lie beyond six median deviations.
_CUTOFF_MEDIANS = 6.0
# Smoothing weights tried by cross-validation, for times in frame steps: from a spline
# that all but interpolates (1e-6) to one stiffer than any motion of this robot (1e8),
# two decades apart, then a quarter-decade apart around the best.
_LAMBDAS = np.logspace(-6.0, 8.0, 8)
_REFINE = np.logspace(-1.0, 1.0, 9)
# Cross-validation folds: frames are numbered modulo _CV_PERIOD; each fold predicts one
# class from the classes at least _CV_GAP away (three in every eight frames), and the
# folds predict every other class.
_CV_PERIOD = 8
_CV_GAP = 3
# The weight is then stiffened a quarter decade at a time while the growth of the
# cross-validation error, frame by frame, stays within this many standard errors of
# that growth: where the data cannot tell two weights apart, the stiffer jitters less
# (in the spirit of Breiman et al.'s one-standard-error rule, but paired, so that the
# small, systematic growth of the error on noise-free fast motion stops it at once).
_SE_FRACTION = 1.0
# A spline is fitted only through at least this many good frames (each fold then fits
# 12 frames and predicts 4).
_MIN_SPLINE_FRAMES = 4 * _CV_PERIOD
# Degree of the local fit that judges frames near the ends of a run, where the full
# degree's one-sided fit passes too much noise to judge anything: a quadratic over
# the frames on one side still tells a frame several mm off from its neighbours.
_END_DEGREE = 2


def smooth_centerlines(
    centerlines_mm: ArrayLike,
    timestamps_s: ArrayLike,
    *,
    half_window: int = 5,
    degree: int = 6,
    reject_outliers: bool = True,
    outlier_half_window: int = 8,
    min_outlier_mm: float = 1.0,
    max_outlier_mm: float = 3.0,
) -> FloatArray:
    """Smooth centrelines over time, point by point: outliers out, then a cross-validated spline.

    Parameters
    ----------
    centerlines_mm : (F, N, 3) float64 centrelines ordered base -> tip, each
        resampled to the same N points, world frame, mm; NaN rows (any NaN in a
        frame) for failed frames.
    timestamps_s : (F,) float64 frame times, s, increasing.
    half_window : frames on each side of a frame that enter its local polynomial
        fit (by index, so the same number of frames at any frame rate). The local
        fits find outliers and decide where any fit can be trusted; the value comes
        from the session-wide spline (the local fit's, with fewer than 32 good frames).
    degree : degree of the local polynomial in time.
    reject_outliers : find wrong frames and leave them out of their neighbours' fits.
    outlier_half_window : half-width of the window in which outliers are sought
        (wider than the smoothing window: a few wrong frames in a row still leave
        enough good ones around them).
    min_outlier_mm : a frame closer than this to the fit (RMS over its points, mm)
        is never an outlier, however smooth the rest is.
    max_outlier_mm : a frame farther than this from the fit is always an outlier,
        however wrong the rest is.

    Returns
    -------
    (F, N, 3) float64 smoothed centrelines, mm; NaN exactly where the input frame
    was failed.
    """
    curves = np.asarray(centerlines_mm, dtype=np.float64)
    times = np.asarray(timestamps_s, dtype=np.float64).reshape(-1)
    if curves.ndim != 3 or curves.shape[2] != 3:
        raise ValueError(f"smooth_centerlines: expected (F, N, 3) centrelines, got {curves.shape}")
    if times.shape != (len(curves),):
        raise ValueError(f"smooth_centerlines: {len(times)} timestamps for {len(curves)} frames")
    if half_window < 1 or degree < 0:
        raise ValueError(
            f"smooth_centerlines: need half_window >= 1 and degree >= 0, got {half_window}, {degree}"
        )
    if len(curves) > 1 and not np.all(np.diff(times) > 0):
        raise ValueError("smooth_centerlines: timestamps must be strictly increasing")

    ok: NDArray[np.bool_] = np.asarray(np.isfinite(curves).all(axis=(1, 2)))
    if not ok.any():
        return curves.copy()
    # Fit in units of the typical frame step: keeps the Vandermonde matrix well conditioned.
    step = float(np.median(np.diff(times))) if len(times) > 1 else 1.0
    offsets = times / step
    active = (
        _inliers(curves, offsets, ok, outlier_half_window, degree, (min_outlier_mm, max_outlier_mm))
        if reject_outliers
        else ok
    )
    fitted, has_fit = _local_fits(curves, offsets, active, half_window, degree)
    spline = _cross_validated_spline(curves, offsets, active)
    if spline is not None:
        # The local fits decide where a fit can be trusted (enough inliers around a
        # frame, as where most frames are wrong there are not); the spline, its weight
        # chosen from the data, gives the value. Inliers beside a trusted frame are
        # trusted too: at the ends of a run the local fit is one-sided and refuses,
        # where the spline is as good as anywhere.
        near = np.convolve(has_fit, np.ones(2 * half_window + 1), mode="same") > 0
        has_fit = has_fit | (active & near)
        fitted = spline
        # An outlier next to trusted frames takes the spline's value, which the
        # frames around it (not the outlier) decide; at the end of a run, where no
        # local fit reaches, it would otherwise keep its wrong value.
        beside = np.convolve(has_fit, np.ones(3), mode="same") > 0
        has_fit = has_fit | (ok & ~active & beside)
    # An outlier with too few inliers around it for the narrow window takes the wide
    # one, even if that fit passes up to twice the noise's RMS (gain 4): an outlier is
    # at least min_outlier_mm off, several times the reconstruction's noise. Only
    # between inliers, though: a high-degree polynomial extrapolates wildly.
    lacking = ok & ~active & ~has_fit
    if lacking.any():
        wide, has_wide = _local_fits(curves, offsets, active, outlier_half_window, degree, max_gain=4.0)
        fill = lacking & has_wide & _surrounded(active, outlier_half_window, degree // 2 + 1)
        fitted[fill], has_fit[fill] = wide[fill], True
    return np.where(has_fit[:, None, None], fitted, curves)


def _cross_validated_spline(
    curves: FloatArray, offsets: FloatArray, active: NDArray[np.bool_]
) -> FloatArray | None:
    """(F, N, 3) smoothing spline through the active frames, evaluated at every frame.

    The weight is the one whose splines through each fold's fitted frames best
    predict its held-out frames (mean squared error over all points and folds),
    stiffened while the data cannot tell the stiffer one apart (_SE_FRACTION), and
    scaled for the full set: its data term sums _CV_PERIOD / (fitted classes) times
    as many residuals. None when there are too few active frames.
    """
    x = offsets[active]
    if len(x) < _MIN_SPLINE_FRAMES:
        return None
    y = curves[active].reshape(len(x), -1)
    coarse = _cv_errors(x, y, _LAMBDAS).mean(axis=1)
    fine = _LAMBDAS[int(np.argmin(coarse))] * _REFINE
    lambdas, errors = list(fine), list(_cv_errors(x, y, fine))
    best = int(np.argmin([e.mean() for e in errors]))
    step = float(_REFINE[1] / _REFINE[0])
    chosen = best
    while lambdas[chosen] < _LAMBDAS[-1]:
        if chosen + 1 == len(lambdas):  # past the fine grid: one more quarter decade
            lambdas.append(lambdas[-1] * step)
            errors.append(_cv_errors(x, y, np.array(lambdas[-1:]))[0])
        growth = errors[chosen + 1] - errors[best]
        if growth.mean() > _SE_FRACTION * growth.std(ddof=1) / np.sqrt(len(growth)):
            break
        chosen += 1
    fitted_share = (_CV_PERIOD - 2 * _CV_GAP + 1) / _CV_PERIOD
    spline = make_smoothing_spline(x, y, lam=float(lambdas[chosen]) / fitted_share)
    return np.asarray(spline(offsets), dtype=np.float64).reshape(curves.shape)


def _cv_errors(x: FloatArray, y: FloatArray, lambdas: FloatArray) -> FloatArray:
    """(L, H) h-block cross-validation errors of a smoothing spline, one row per weight in
    ``lambdas``: each held-out frame's squared prediction error, summed over its values.

    x : (K,) active frame times; y : (K, M) their values. Frames are classed by
    index modulo _CV_PERIOD; a fold predicts one class from the classes at least
    _CV_GAP away, never extrapolating.
    """
    classes = np.arange(len(x)) % _CV_PERIOD
    errors: list[FloatArray] = []
    for held_out in range(0, _CV_PERIOD, 2):
        distance = np.abs(classes - held_out)
        distance = np.minimum(distance, _CV_PERIOD - distance)
        fit, test = distance >= _CV_GAP, distance == 0
        test &= (x > x[fit][0]) & (x < x[fit][-1])
        predicted = _spline_predictions(x[fit], y[fit], x[test], lambdas)
        errors.append(np.sum((predicted - y[test]) ** 2, axis=2))
    return np.concatenate(errors, axis=1)


def _spline_predictions(x: FloatArray, y: FloatArray, x_new: FloatArray, lambdas: FloatArray) -> FloatArray:
    """(L, T, M) values at ``x_new`` of the cubic smoothing splines through ``(x, y)``, one per weight.

    x : (K,) increasing, K >= 3; y : (K, M); x_new : (T,) within [x[0], x[-1]].
    Each spline minimises ``sum((y - f(x))**2) + lam * integral(f''**2)``, as
    ``make_smoothing_spline(x, y, lam=lam)`` does (same curves, to rounding), but in
    Reinsch's form (Green & Silverman 1994, ch. 2): the values g and second
    derivatives gamma of the natural spline at the knots solve the banded system
    ``(R + lam Q'Q) gamma = Q'y``, ``g = y - lam Q gamma``. Everything but that
    solve is built once for all weights. The cross-validation fits ~70 splines per
    session and SciPy rebuilds its matrices for each; this way the smoothing of the
    900-frame demo, serial at the end of a run, takes 0.14 s instead of 0.25 s.
    """
    h = np.diff(x)
    inv_h = 1.0 / h
    # Q (K, K-2) second differences: column j is 1/h_j, -1/h_j - 1/h_j+1, 1/h_j+1 in rows j..j+2.
    q = np.stack([inv_h[:-1], -(inv_h[:-1] + inv_h[1:]), inv_h[1:]])
    qty = q[0, :, None] * y[:-2] + q[1, :, None] * y[1:-1] + q[2, :, None] * y[2:]
    qtq = ((q**2).sum(axis=0), q[1, :-1] * q[0, 1:] + q[2, :-1] * q[1, 1:], q[2, :-2] * q[0, 2:])
    r_diagonal, r_off = (h[:-1] + h[1:]) / 3.0, h[1:-1] / 6.0  # R, tridiagonal
    # Each new point in its knot interval [x_i, x_i+1], and the cubic's weights there
    # on g_i, g_i+1, gamma_i, gamma_i+1.
    i = np.clip(np.searchsorted(x, x_new, side="right") - 1, 0, len(x) - 2)
    a, b, hi = (x_new - x[i])[:, None], (x[i + 1] - x_new)[:, None], h[i][:, None]
    w_g0, w_g1 = b / hi, a / hi
    w_gamma0, w_gamma1 = -a * b / 6.0 * (1.0 + w_g0), -a * b / 6.0 * (1.0 + w_g1)

    out = np.empty((len(lambdas), len(x_new), y.shape[1]))
    band = np.zeros((3, len(x) - 2))  # upper banded form for solveh_banded
    gamma = np.zeros_like(y)  # a natural spline's ends have gamma = 0
    slopes = np.zeros((len(x) + 1, y.shape[1]))  # (gamma_j+1 - gamma_j) / h_j, 0-padded
    for values, lam in zip(out, lambdas, strict=True):
        band[2], band[1, 1:], band[0, 2:] = r_diagonal + lam * qtq[0], r_off + lam * qtq[1], lam * qtq[2]
        gamma[1:-1] = solveh_banded(band, qty, check_finite=False)
        slopes[1:-1] = np.diff(gamma, axis=0) * inv_h[:, None]
        g0 = y[i] - lam * (slopes[i + 1] - slopes[i])  # (Q gamma)_j = slopes_j+1 - slopes_j
        g1 = y[i + 1] - lam * (slopes[i + 2] - slopes[i + 1])
        values[:] = w_g0 * g0 + w_g1 * g1 + w_gamma0 * gamma[i] + w_gamma1 * gamma[i + 1]
    return out


def _surrounded(active: NDArray[np.bool_], half_window: int, count: int) -> NDArray[np.bool_]:
    """(F,) bool: frames with at least ``count`` active frames on each side within the window."""
    cum = np.concatenate([[0], np.cumsum(active)])
    idx = np.arange(len(active))
    before = cum[idx] - cum[np.maximum(idx - half_window, 0)]
    after = cum[np.minimum(idx + half_window + 1, len(active))] - cum[idx + 1]
    return np.asarray((before >= count) & (after >= count))


def _inliers(
    curves: FloatArray,
    offsets: FloatArray,
    ok: NDArray[np.bool_],
    half_window: int,
    degree: int,
    cutoff_mm: tuple[float, float],
) -> NDArray[np.bool_]:
    """(F,) bool: the ok frames left once outliers are removed, one per window per pass.

    ``cutoff_mm`` : (smallest, largest) deviation cut-off, mm.
    """
    active = ok.copy()
    # Each pass removes at least one frame, so this bound is never what stops it.
    for _ in range(len(curves)):
        fitted, has_fit = _local_fits(curves, offsets, active, half_window, degree)
        if degree > _END_DEGREE and not has_fit[ok].all():
            # Frames without a usable fit (near the ends of a run) are judged by a
            # lower-degree one, or an outlier there would never be found.
            low, has_low = _local_fits(curves, offsets, active, half_window, _END_DEGREE, only=ok & ~has_fit)
            fitted[has_low], has_fit = low[has_low], has_fit | has_low
        outliers = _outliers(curves, fitted, active & has_fit, half_window, cutoff_mm)
        if not outliers.any():
            break
        active &= ~outliers
    return active


def _outliers(
    curves: FloatArray,
    fitted: FloatArray,
    judged: NDArray[np.bool_],
    half_window: int,
    cutoff_mm: tuple[float, float],
) -> NDArray[np.bool_]:
    """(F,) bool: judged frames far from their fit and the farthest in their window."""
    if not judged.any():
        return np.zeros(len(curves), dtype=bool)
    deviation = np.full(len(curves), -np.inf)
    deviation[judged] = np.sqrt(np.mean(np.sum((curves[judged] - fitted[judged]) ** 2, axis=2), axis=1))
    min_mm, max_mm = cutoff_mm
    cutoff = min(max(_CUTOFF_MEDIANS * float(np.median(deviation[judged])), min_mm), max_mm)
    # Window maximum by a sliding view over the padded deviations.
    padded = np.pad(deviation, half_window, constant_values=-np.inf)
    window_max = np.lib.stride_tricks.sliding_window_view(padded, 2 * half_window + 1).max(axis=1)
    return np.asarray(judged & (deviation > cutoff) & (deviation >= window_max))


def _local_fits(
    curves: FloatArray,
    offsets: FloatArray,
    active: NDArray[np.bool_],
    half_window: int,
    degree: int,
    *,
    max_gain: float = 1.0,
    only: NDArray[np.bool_] | None = None,
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Each ok frame's local polynomial fit over the active frames of its window.

    Parameters
    ----------
    curves : (F, N, 3) float64, NaN rows for failed frames (never active).
    offsets : (F,) float64 frame times in median frame steps.
    active : (F,) bool frames that enter the fits.
    max_gain : largest usable noise gain (see :func:`_local_fit_weights`).
    only : (F,) bool, fit only these frames (default: every ok frame).

    Returns
    -------
    fitted : (F, N, 3) float64 fit at each frame; NaN where there is no usable fit.
    has_fit : (F,) bool, True where the frame is ok and its fit is usable.
    """
    frames = len(curves)
    fitted = np.full_like(curves, np.nan)
    has_fit = np.zeros(frames, dtype=bool)
    # At a steady frame rate most windows have the same relative offsets, hence the
    # same weights: each set is computed once (keyed to 1e-9 frame steps, far below
    # any real timing difference).
    weights: dict[bytes, FloatArray | None] = {}
    wanted = np.isfinite(curves).all(axis=(1, 2))
    if only is not None:
        wanted &= only
    for f in np.flatnonzero(wanted).tolist():
        lo, hi = max(0, f - half_window), min(frames, f + half_window + 1)
        used = lo + np.flatnonzero(active[lo:hi])
        relative = offsets[used] - offsets[f]
        key = np.round(relative, 9).tobytes()
        if key not in weights:
            weights[key] = _local_fit_weights(relative, degree, max_gain=max_gain)
        coeffs = weights[key]
        if coeffs is not None:
            fitted[f] = np.tensordot(coeffs, curves[used], axes=1)
            has_fit[f] = True
    return fitted, has_fit


def _local_fit_weights(offsets: FloatArray, degree: int, *, max_gain: float = 1.0) -> FloatArray | None:
    """Coefficients c such that c @ y is the least-squares polynomial fit to y at offset 0.

    Parameters
    ----------
    offsets : (K,) float64 sample times relative to the evaluated one, in frame steps.
    degree : polynomial degree.
    max_gain : largest usable noise gain sum(c**2); 1 means the fit must pass less
        noise than the raw sample.

    Returns
    -------
    (K,) float64 coefficients, or None when the fit is not worth using: too few
    samples to be a fit rather than an interpolation, or a noise gain >= max_gain.
    """
    if len(offsets) < degree + 2:
        return None
    vander = np.vander(offsets, degree + 1, increasing=True)  # (K, degree + 1)
    # Row 0 of the pseudo-inverse evaluates the fitted polynomial's constant term.
    coeffs = np.linalg.pinv(vander)[0]
    if float(coeffs @ coeffs) >= max_gain:
        return None
    return np.asarray(coeffs, dtype=np.float64)
