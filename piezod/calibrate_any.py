"""``piezod calibrate`` on any waveform: which model the recordings determine, and the fit.

The thesis model (3.8) describes the *steady loop of a periodic triangular scan*: it needs
every experiment to be such a scan (one complete loop at least; a one-period triangle as
instruments export it, one loop per block, counts, :attr:`piezod.scan_inference.ScanInfo.wraps`).
The dynamic model (:mod:`piezod.model.dynamic`: the hysteresis ODE (2.21) with log creep, run
through the whole session) takes any waveform: sines, ramps, minor loops, steps, holds.

:func:`choose_model` picks (3.8) when every experiment is a periodic triangular scan and the
dynamic model otherwise, and says why; :func:`calibrate_any` fits the chosen one with the
existing fitters (:func:`piezod.calibrate.calibrate`, :func:`piezod.calibrate_dynamic.calibrate_dynamic`)
and returns which it was. Pure dispatch: no fitting code of its own.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Literal, cast

from piezod import calibrate as thesis_cal
from piezod import calibrate_dynamic as dynamic_cal
from piezod.config import AxisName, ScannerConfig
from piezod.errors import CalibrationError
from piezod.extensions import session_origin_unix_s
from piezod.model.params import ThesisParams
from piezod.recording import Experiment

ModelName = Literal["thesis", "dynamic"]
#: ``--model`` choices of ``piezod calibrate``.
MODEL_CHOICES: tuple[str, ...] = ("auto", "thesis", "dynamic")


@dataclass(frozen=True)
class ModelChoice:
    """Which model a calibration fits, and why.

    Attributes
    ----------
    model
        ``thesis`` (3.8) or ``dynamic`` (ODE (2.21) + log creep).
    reason
        One line: why this model (the first experiment that is not a triangular scan, or that
        all are).
    """

    model: ModelName
    reason: str


def choose_model(experiments: Sequence[Experiment], requested: str = "auto") -> ModelChoice:
    """The model the recordings determine (``requested``: ``auto``, ``thesis`` or ``dynamic``).

    Raises
    ------
    CalibrationError
        ``thesis`` requested for recordings that are not all periodic triangular scans (the
        message names the experiment and why), or an unknown ``requested``.
    """
    if requested not in MODEL_CHOICES:
        raise CalibrationError(f"unknown model {requested!r}; choose one of {', '.join(MODEL_CHOICES)}")
    if not experiments:
        raise CalibrationError("no experiments to calibrate")
    if requested == "dynamic":
        return ModelChoice("dynamic", "requested (--model dynamic)")
    for e in experiments:
        info = e.scan()
        if not info.is_scan:
            why = (
                f"experiment {e.describe()} is not a periodic triangular scan ({info.kind}"
                + (f": {info.reason}" if info.reason else "")
                + ")"
            )
            if requested == "thesis":
                e.require_scan()  # the reader's error: file, line and reason
            return ModelChoice(
                "dynamic", why + ": the dynamic model (ODE 2.21 + log creep) takes any waveform"
            )
    if requested == "thesis":
        return ModelChoice("thesis", "requested (--model thesis)")
    return ModelChoice("thesis", "every experiment is a periodic triangular scan: the thesis model (3.8)")


@dataclass(frozen=True, eq=False)
class AnyCalibration:
    """A calibration of either model.

    Attributes
    ----------
    choice
        The model and why.
    fit
        The fitter's result: (3.8) or the dynamic model, as ``choice.model`` says.
    """

    choice: ModelChoice
    fit: thesis_cal.CalibrationResult | dynamic_cal.DynamicCalibrationResult

    @property
    def thesis(self) -> thesis_cal.CalibrationResult | None:
        """The (3.8) fit, or None."""
        return self.fit if isinstance(self.fit, thesis_cal.CalibrationResult) else None

    @property
    def dynamic(self) -> dynamic_cal.DynamicCalibrationResult | None:
        """The dynamic fit, or None."""
        return self.fit if isinstance(self.fit, dynamic_cal.DynamicCalibrationResult) else None

    @property
    def success(self) -> bool:
        """Whether the solver converged."""
        return bool(self.fit.success)

    @property
    def message(self) -> str:
        """The solver's message."""
        return self.fit.message


def calibrate_any(
    experiments: Sequence[Experiment],
    *,
    model: str = "auto",
    start: ThesisParams | None = None,
    loss: str = "linear",
    f_scale: float | None = None,
    fix: Iterable[str] = (),
    skip_loops: int = 0,
    max_samples_per_loop: int | None = 2048,
    on_eval: Callable[[int], None] | None = None,
) -> AnyCalibration:
    """Fit the model :func:`choose_model` picks.

    Parameters
    ----------
    experiments
        The experiments (one axis).
    model
        ``auto``, ``thesis`` or ``dynamic``.
    start, loss, f_scale, fix, skip_loops, max_samples_per_loop
        Options of the (3.8) fit (:func:`piezod.calibrate.calibrate`). The dynamic fit takes
        ``fix`` (its own parameter names) and ``max_samples_per_loop`` and starts from the
        data (:func:`piezod.calibrate_dynamic.auto_start`; ``start`` is a (3.8) start and not
        used); ``loss``, ``f_scale`` and ``skip_loops`` are (3.8) options only.
    on_eval
        Progress callback.

    Raises
    ------
    CalibrationError
        An option that the chosen model does not take, or the fit failed.
    """
    choice = choose_model(experiments, model)
    if choice.model == "thesis":
        res = thesis_cal.calibrate(
            experiments,
            start=start,
            loss=loss,
            f_scale=f_scale,
            fix=fix,
            skip_loops=skip_loops,
            max_samples_per_loop=max_samples_per_loop,
            on_eval=on_eval,
        )
        return AnyCalibration(choice, res)
    if loss != "linear" or f_scale is not None or skip_loops:
        raise CalibrationError(
            f"--loss, --f-scale and --skip-loops are options of the thesis model (3.8); {choice.reason}"
        )
    fixed = tuple(fix)
    unknown = set(fixed) - set(dynamic_cal.PARAM_NAMES)
    if unknown:
        raise CalibrationError(
            f"cannot fix {', '.join(sorted(unknown))} in the dynamic model (its parameters: "
            f"{', '.join(dynamic_cal.PARAM_NAMES)}); {choice.reason}"
        )
    per_loop = max_samples_per_loop or 512
    try:
        res_d = dynamic_cal.calibrate_dynamic(
            experiments, fix=fixed, max_samples_per_loop=per_loop, on_eval=on_eval
        )
    except CalibrationError as exc:
        # A free power-law exponent can carry the creep out of the model's domain (total creep
        # >= 0.9) when the data hold something creep is not (a lag): the log law is the fallback.
        if "model's domain" not in str(exc) or "creep_exponent" in fixed:
            raise
        res_d = dynamic_cal.calibrate_dynamic(
            experiments, fix=(*fixed, "creep_exponent"), max_samples_per_loop=per_loop, on_eval=on_eval
        )
        choice = ModelChoice(
            choice.model,
            f"{choice.reason}; creep_exponent held at 0 (the log law), free it left the model's domain",
        )
    return AnyCalibration(choice, res_d)


def result_json(result: AnyCalibration, *, inputs: Sequence[str] = ()) -> dict[str, Any]:
    """The JSON of ``piezod calibrate --json``: the fitter's keys plus ``model`` and ``model_reason``."""
    fit = result.fit
    if isinstance(fit, thesis_cal.CalibrationResult):
        doc = thesis_cal.result_json(fit, inputs=inputs)
    else:
        doc = dynamic_cal.result_json(fit, inputs=inputs)
    doc["model"] = result.choice.model
    doc["model_reason"] = result.choice.reason
    return doc


def calibrated_config(
    result: AnyCalibration,
    *,
    axis: str = "x",
    base: ScannerConfig | None = None,
    inputs: Sequence[str] = (),
    voltage_span_v: tuple[float, float] | None = None,
) -> ScannerConfig:
    """The scanner config of the fit (``model: thesis`` or ``model: dynamic`` on ``axis``).

    A dynamic fit without a base config gets a ``thesis:`` section (the engine plans periodic
    scans with it) from the base, else the fitted hysteresis ``alpha, b, u`` with no creep
    terms (``a1 = a2 = a3 = 0``: (3.8) reduces to the steady loop of (2.21)).
    """
    fit = result.fit
    if isinstance(fit, thesis_cal.CalibrationResult):
        return thesis_cal.calibrated_config(
            fit, axis=axis, base=base, inputs=inputs, voltage_span_v=voltage_span_v
        )
    p = fit.params
    thesis = None
    if base is None or axis not in base.axes:
        thesis = ThesisParams(
            p.alpha_per_v, p.b_um_per_v, p.u_um_per_v, tau_s=1.0, a1=0.0, a2_per_v=0.0, a3=0.0
        )
    return dynamic_cal.calibrated_config(
        fit, axis=axis, base=base, thesis=thesis, inputs=inputs, voltage_span_v=voltage_span_v
    )


def with_tracking_bound(config: ScannerConfig, axis: str, min_line_s: float) -> ScannerConfig:
    """``config`` with ``axis``'s ``tracking_min_line_s`` set: the sensitivity tracker
    (:mod:`piezod.service.tracking`) learns only from lines about that long or longer."""
    return config.with_axis(cast(AxisName, axis), tracking_min_line_s=min_line_s)


def shortest_line_s(experiments: Sequence[Experiment]) -> float | None:
    """The shortest line (rising or falling half period) of the experiments' periodic waveforms (s).

    What an offline calibration writes as the axis's ``tracking_min_line_s``: the daemon's
    sensitivity tracker then learns only from lines the recordings measured the rate dependence
    for, as after ``piezod calibrate --sim/--port`` (:func:`piezod.stagecal.with_tracking_bound`).
    None when no experiment has a complete half period.
    """
    lines = []
    for e in experiments:
        info = e.scan()
        f = info.frequency_hz
        if not (math.isfinite(f) and f > 0):
            continue
        duty = info.duty if math.isfinite(info.duty) and 0.0 < info.duty < 1.0 else 0.5
        lines.append(min(duty, 1.0 - duty) / f)
    return min(lines) if lines else None


def recorded_mid_unix_s(experiments: Sequence[Experiment]) -> float:
    """When the experiments were measured, on the wall clock (Unix time, s): the sample-weighted
    mean of their middles, each recording's clock placed by its header's ``started_utc``
    (:func:`piezod.extensions.session_origin_unix_s`). What an offline calibration writes as
    ``calibration.recorded_utc``; ``nan`` when a recording does not say when it started (other
    tools' files) or an experiment has no file.

    Raises
    ------
    RecordingError
        A header's ``started_utc`` is unreadable (names the file).
    """
    origins: dict[str, float] = {}
    total = weight = 0.0
    for e in experiments:
        if e.path is None or len(e.t_s) == 0:
            return math.nan
        if e.path not in origins:
            origins[e.path] = session_origin_unix_s(e.path)
        mid = origins[e.path] + 0.5 * (float(e.t_s[0]) + float(e.t_s[-1]))
        if not math.isfinite(mid):
            return math.nan
        total += mid * len(e.t_s)
        weight += len(e.t_s)
    return total / weight if weight else math.nan


__all__ = [
    "MODEL_CHOICES",
    "AnyCalibration",
    "ModelChoice",
    "calibrate_any",
    "calibrated_config",
    "choose_model",
    "recorded_mid_unix_s",
    "result_json",
    "shortest_line_s",
    "with_tracking_bound",
]
