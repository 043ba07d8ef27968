"""The run's warnings on its error estimate: uncertain (its interval wide), no estimate at all
(below zero), or blind to what a sensor erring grossly may also do (``TrackRun.check``,
:mod:`torchsvs.track_run`, adds them)."""

from __future__ import annotations

from torchsvs.accuracy import Accuracy
from torchsvs.datasets.rows import RowReport
from torchsvs.fitting.outliers import has_gross_errors
from torchsvs.recipes import short

#: The error estimate is called uncertain where its interval reaches beyond this many times the
#: estimate. Measured on the recorded-tracks benchmarks (263 runs, σ 3-250 m, noise read off
#: the data): the 26 estimates more than 15% off the truth (0.34-0.73× at σ 250 m, where a 4%
#: error in the noise read moves SURE's r(2·div − n) term by most of the error itself; 1.3× on
#: 10 s scans at σ 3 m) reach 1.89-6.5 times theirs; the 237 within 15%, up to 2.02 (the truth
#: inside the interval in 252 of the 263).
UNCERTAIN_REACH = 1.8


def gross_errors(report: RowReport) -> str | None:
    """A warning where the outlier screen set aside more than
    :data:`~torchsvs.fitting.outliers.GROSS_ERROR_SHARE` of the positions
    (:func:`~torchsvs.fitting.outliers.has_gross_errors`): the error estimate counts white,
    unbiased noise only, and a sensor that errs grossly that often may err in ways it cannot
    see."""
    outliers, measured = report.notes.get("outliers", 0), report.measurement
    if not has_gross_errors(outliers, measured):
        return None
    return (
        f"measurements: {outliers} positions ({outliers / measured:.2%}) lay far off the path "
        "their neighbours agree on, where the noise explains about one in a million; they were "
        "set aside, but a sensor with gross errors may also have errors the error estimate "
        "cannot see (a bias, errors shared between rows): it counts white noise only, and the "
        "true error may be well above it"
    )


def uncertain_estimate(found: Accuracy, exact: bool = True) -> str | None:
    """A warning where the error estimate's interval reaches beyond :data:`UNCERTAIN_REACH`
    times the estimate, naming what makes it so: the noise level read off the data (where it
    widens the interval to over twice the sampling error's), else the estimate's own sampling
    error (``exact``: the estimator's divergence is exact, not probed)."""
    low, high = found.interval
    if not high > UNCERTAIN_REACH * found.estimated_rmse:
        return None
    text = (
        f"the estimated position error {found.estimated_rmse:.3g} m is uncertain: the error "
        f"could be anywhere in {low:.3g}-{high:.3g} m; "
    )
    sampling_low, sampling_high = found.sampling_interval
    if found.noise_estimated and high - low > 2.0 * (sampling_high - sampling_low):
        return text + (
            f"most of that is the measurement noise read off the data ({short(found.meas_std)} "
            "m, within its uncertainty): the estimate subtracts the noise's share from the "
            "residuals, so a small error in the noise moves it far; give --meas-std with the "
            "sensor's noise if known"
        )
    return text + (
        "its own sampling error is large: the estimate is the residuals less the noise's "
        "share, each far larger than the error at this noise, over these positions"
        + ("" if exact else " (and this estimator's sensitivity to them is probed at random)")
    )


def below_zero_estimate(found: Accuracy) -> str:
    """The warning where the error estimate is surely below zero (:attr:`~torchsvs.accuracy.
    Accuracy.below_zero`): SURE at the true noise averages the MSE, never below zero, so the
    noise it assumes is too high, and it is no error estimate. Where a user gives the noise as
    a bound (a 95% one, twice σ) rather than σ, the run smooths more than the data need and
    would otherwise print an error of 0 m."""
    source = "read off the data" if found.noise_estimated else "given"
    bound = (
        ""
        if found.zero_at_noise is None
        else f" (about {short(found.zero_at_noise)} m at most: there the estimate is zero)"
    )
    advice = (
        "give --meas-std with the sensor's noise if known"
        if found.noise_estimated
        else "give --meas-std as the sensor's standard deviation (1σ, not a bound such as a 95% "
        "one), or leave it out to read the noise off the data"
    )
    return (
        f"the error estimate came out below zero (MSE {found.mse:.3g} ± "
        f"{found.mse_standard_error:.2g} m² per point), so it is no estimate: the measurement "
        f"noise {source} ({short(found.meas_std)} m) is more than the residuals about the "
        f"estimate allow{bound}; the estimates smooth more than the data need, and "
        f"the measurements' own error is below the {found.measurement_rmse:.3g} m that noise "
        f"says; {advice}"
    )
