"""The Bouc-Wen/Duhem member's fit on a session narrower than its rate box was made for: a slice of
the real P-885 identification run (0-3.6 V). Session 6's search returned a law with ``b`` and
``-c`` near 5e7 um/V cancelling (a rate too low to bend within the session's voltages), which the
slope limit on ``c`` turned into a 3e7 um training RMS."""

from __future__ import annotations

import math
from functools import cache
from pathlib import Path

import pytest

from piezod.calibrate_dynamic import DynamicCalibrationData, prepare_dynamic
from piezod.calibrate_family import choose_model, fit_family
from piezod.errors import CalibrationError
from piezod.model.boucwen import BoucWenParams
from piezod.recording import Experiment, read_experiments

DATA = Path(__file__).resolve().parents[1] / "piezod" / "data" / "real" / "pi-p885"


@cache
def _p885_slice(seconds: float = 12.0) -> DynamicCalibrationData:
    """The first ``seconds`` of the real identification run (1 Hz raised sine, 0-3.6 V)."""
    e = read_experiments([DATA / "identification.csv"])[0]
    keep = e.t_s <= e.t_s[0] + seconds
    part = Experiment(e.label, e.axis, e.t_s[keep], e.voltage_v[keep], e.position_um[keep])
    return prepare_dynamic(
        [part],
        max_samples_per_loop=128,
        max_samples_per_experiment=1 << 16,
        rest_voltage_v=float(part.voltage_v[0]),
    )


def test_the_bouc_wen_fit_on_a_narrow_real_session_is_sane() -> None:
    data = _p885_slice()
    fit = fit_family(data, "bouc-wen", skip_s=1.0)
    h = fit.params.hysteresis
    assert isinstance(h, BoucWenParams)
    # the travel is ~40 um over 3.6 V: a sane law has b and -c of order 10 um/V, not 5e7
    assert h.b_um_per_v < 100.0 and -h.c_um_per_v < 100.0, h
    assert math.isfinite(fit.rms_um) and fit.rms_um < 0.3, fit.rms_um


@pytest.fixture
def _rates_too_low(monkeypatch: pytest.MonkeyPatch) -> None:
    """A rate box in which the law cannot bend within the slice's 3.6 V (k x span <= 1e-3)."""
    monkeypatch.setattr("piezod.calibrate_family.BW_RATE_BOUNDS", (1e-4, 3e-4))
    monkeypatch.setattr("piezod.calibrate_family.BW_SPAN_REF_V", 0.0)


@pytest.mark.usefixtures("_rates_too_low")
def test_a_bouc_wen_search_with_no_admissible_rates_raises() -> None:
    with pytest.raises(CalibrationError, match="bouc-wen") as info:
        fit_family(_p885_slice(), "bouc-wen", skip_s=1.0)
    assert "\n" not in str(info.value)


@pytest.mark.usefixtures("_rates_too_low")
def test_choose_model_skips_a_failed_law_and_reports_it() -> None:
    data = _p885_slice()
    choice = choose_model(data, laws=("coleman-hodgdon", "bouc-wen"), creep_drivers=("position",))
    assert choice.chosen == "family/coleman-hodgdon"
    assert set(choice.failed) == {"family/bouc-wen"}
    assert "family/bouc-wen" not in choice.heldout_rms_um
    row = [line for line in choice.table().splitlines() if line.startswith("family/bouc-wen")]
    assert len(row) == 1 and "failed" in row[0]
    with pytest.raises(CalibrationError, match="no model to choose"):
        choose_model(data, laws=("bouc-wen",), creep_drivers=("position",))


def test_a_fit_started_from_a_law_fitted_on_nearly_the_same_data_finds_it_cheaper() -> None:
    """The runtime parts' profiles refit one member many times: started from the first fit's law,
    the Bouc-Wen fit skips its search and lands where the search does."""
    data = _p885_slice()
    cold = fit_family(data, "bouc-wen", skip_s=1.0)
    start = cold.params.hysteresis
    assert isinstance(start, BoucWenParams)
    near = _p885_slice(11.0)  # nearly the same data: a second less
    searched = fit_family(near, "bouc-wen", skip_s=1.0)
    warm = fit_family(near, "bouc-wen", skip_s=1.0, start=start)
    assert warm.rms_um <= searched.rms_um * 1.01
    assert warm.nfev < 0.5 * searched.nfev
