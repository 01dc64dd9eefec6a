"""What the model family leaves on the real P-885 stack, taken apart.

Usage::

    python tools/p885_anatomy.py [--plays 32]

Four measurements on ``piezod/data/real/pi-p885`` (real data), each law fitted by
:func:`piezod.calibrate_family.fit_family` with the recording's documented one-sample sensor lag
removed and an exact one-sample drive lag (the best setting of ``tools/model_family_p885.py``):

1. **The identification fit's own residual**, folded over the 1 Hz period (the run is one raised
   sine at constant amplitude): the part locked to the excitation's phase, the slow part (1 s
   average of what is left) and the rest, beside the sensor noise floor.
2. **The validation run predicted, stretch by stretch** (full amplitude, decay, rest, growth; the
   first 36 s open loop, then the authors' compensated input): RMS, mean and RMS about the mean
   of the prediction error per stretch (one offset per experiment and one gain for the run fitted,
   as the family tool does).
3. **Nested loops in the training data**: fitted on one experiment of the validation run (open
   loop / compensated; the state carried through both), the other predicted.
4. **The identification run's unknown history**: the same fits with the stage at rest at 0 V
   before the record instead of at its first voltage.
5. **A loop centre driven by the cycling** (cyclic creep): an offset that builds up while the
   stage cycles and relaxes at rest, ``sum_k w_k LP_tau_k(|dV/dt|)`` (first-order low passes,
   ``tau`` 0.3-30 s, weights of either sign), fitted by least squares to the play law's residual
   on the identification run and carried to the validation run; and, as an upper bound of what
   such a term can do, fitted on the validation run itself.
6. **What a law can fit at all**: every member fitted on the validation run itself (its training
   RMS: a lower bound of what that member can reach on it), and a full Preisach density -- every
   relay of a 30 x 30 grid over the drive span (465 relays, signed weights) plus voltage-creep
   columns (8 relaxation times, 10 ms-30 s), by ridge least squares -- fitted on the validation
   run itself, on the identification run with the validation run's compensated part (nested
   loops in the training data) predicting its open-loop part, and on the identification run
   alone predicting the validation run.
7. **What the full Preisach density leaves** on the run it is fitted to: the residual's RMS at
   rest and at full amplitude by band (below 5 Hz, 5-30 Hz, above 30 Hz), the narrow lines at 58
   and 100 Hz, and whether the part locked to the 1 Hz drive over 7 cycles carries to the next 7
   and to 7 cycles 27 s after the first.

Every score is an RMS in um; "x" is the ratio to the validation run's noise floor (third
differences, :func:`piezod.audit.residuals.noise_floor`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.signal import lfilter

sys.path.insert(0, str(Path(__file__).resolve().parent))

from model_family_p885 import _prepare, prediction_error

from piezod.audit.residuals import noise_floor
from piezod.calibrate_data import DynamicCalibrationData
from piezod.calibrate_family import fit_family, settled_rows
from piezod.errors import CalibrationError
from piezod.model.family import FamilyParams

F64 = NDArray[np.float64]
SKIP_S = 1.0
ACTIVITY_TAUS_S = (0.3, 1.0, 3.0, 10.0, 30.0)
STRETCHES = (
    ("open loop, full amplitude", 1.0, 16.0),
    ("open loop, decay", 16.0, 20.0),
    ("open loop, rest", 20.0, 24.0),
    ("open loop, growth", 24.0, 28.0),
    ("open loop, full amplitude", 28.0, 36.0),
    ("compensated, full amplitude", 37.0, 48.0),
    ("compensated, decay", 48.0, 52.0),
    ("compensated, rest", 52.0, 56.0),
    ("compensated, growth", 56.0, 60.0),
    ("compensated, full amplitude", 60.0, 71.0),
)


def _error(data: DynamicCalibrationData, params: FamilyParams, rows: NDArray[np.bool_]) -> F64:
    """Prediction minus measurement on ``rows``: offsets per experiment, one gain (nuisance)."""
    out: F64 = prediction_error(data, params, rows)[0]
    return out


def _rms(a: F64) -> float:
    return float(np.sqrt(np.mean(a**2)))


def _activity(data: DynamicCalibrationData, rows: NDArray[np.bool_]) -> F64:
    """Low-passed |dV/dt| at every compared sample, one column per time constant, each column
    centred per experiment on ``rows`` (the per-experiment offsets are nuisance parameters)."""
    v = data.hysteresis_voltage_v[data.compared]
    dt = 0.005
    rate = np.abs(np.gradient(v)) / dt
    cols = []
    for tau in ACTIVITY_TAUS_S:
        k = np.exp(-dt / tau)
        cols.append(lfilter([1.0 - k], [1.0, -k], rate))
    f = np.column_stack(cols)
    return _centred(data, f, rows)


def _centred(data: DynamicCalibrationData, a: F64, rows: NDArray[np.bool_]) -> F64:
    out = np.array(a, dtype=float)
    for s, c in zip(data.starts, data.counts, strict=True):
        sl = slice(int(s), int(s + c))
        out[sl] -= out[sl][rows[sl]].mean(axis=0)
    return out


PREISACH_GRID = 30
PREISACH_TAUS_S = tuple(float(t) for t in np.logspace(-2.0, 1.5, 8))
PREISACH_RIDGE = 1e-5


def _preisach_columns(data: DynamicCalibrationData, lo: float, hi: float) -> F64:
    """Relay states (+-1) of a triangular Preisach grid and voltage-creep deviations, at the
    compared samples; the relays start demagnetised at the session's rest voltage."""
    g = np.linspace(lo, hi, PREISACH_GRID + 1)
    up, down = (a.ravel() for a in np.meshgrid(g, g, indexing="ij"))
    keep = up >= down
    up, down = up[keep], down[keep]
    v = data.grid_voltage_v
    v0 = data.rest_voltage_v
    state = np.where(up + down < 2.0 * v0, 1.0, -1.0)
    state[up <= v0], state[down >= v0] = 1.0, -1.0
    states = np.empty((v.size, up.size))
    for n, x in enumerate(v):
        state[x >= up] = 1.0
        state[x <= down] = -1.0
        states[n] = state
    creep = []
    for tau in PREISACH_TAUS_S:
        k = np.exp(-0.005 / tau)
        creep.append(v - lfilter([1.0 - k], [1.0, -k], v, zi=[k * v[0]])[0])
    cols: F64 = np.column_stack([v, v * v, states, np.column_stack(creep)])[data.compared]
    return cols


def _ridge(x: F64, y: F64) -> F64:
    a = x.T @ x
    lam = PREISACH_RIDGE * float(np.trace(a)) / a.shape[0]
    out: F64 = np.linalg.solve(a + lam * np.eye(a.shape[0]), x.T @ y)
    return out


def _scored(data: DynamicCalibrationData, pred: F64, rows: NDArray[np.bool_]) -> float:
    """RMS of the measurement against a prediction on ``rows``, one offset per experiment and one
    gain fitted there (the nuisance parameters of the family tool)."""
    exp = np.repeat(np.arange(data.n_experiments), data.counts)[rows]
    a = np.column_stack([pred[rows], *(exp == k for k in range(data.n_experiments))]).astype(float)
    coef, *_ = np.linalg.lstsq(a, data.position_um[rows], rcond=None)
    return _rms(data.position_um[rows] - a @ coef)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[1])
    ap.add_argument("--plays", type=int, default=32)
    args = ap.parse_args()
    _, ident = _prepare("identification.csv", 1, 1.0)
    valid_exps, valid = _prepare("validation.csv", 1, 1.0)
    floor = float(np.sqrt(np.mean([noise_floor(np.asarray(e.position_um)) ** 2 for e in valid_exps])))
    floor_id = noise_floor(np.asarray(ident.position_um))
    members = (("prandtl-ishlinskii", "position"), ("generalised-play", "voltage"))
    fits = {
        m: fit_family(ident, m[0], plays=args.plays, skip_s=SKIP_S, creep_driver=m[1], fit_lag=False)
        for m in members
    }
    print(f"noise floor: identification {floor_id:.4f} um, validation {floor:.4f} um")

    print("\n1. the identification fit's residual, folded over the 1 Hz period")
    period = round(1.0 / float(ident.experiments[0].frequency_hz) / 0.005)
    keep = settled_rows(ident, SKIP_S)
    idx = np.arange(keep.size)
    for (law, driver), fit in fits.items():
        r = -_error(ident, fit.params, np.ones(keep.size, dtype=bool))
        r = r - r[keep].mean()
        phase = idx % period
        locked = np.array([r[keep & (phase == k)].mean() for k in range(period)])
        rest = r - locked[phase]
        slow = np.convolve(rest, np.ones(period) / period, mode="same")
        inner = keep & (idx >= idx[keep][0] + period // 2) & (idx <= idx[-1] - period // 2)
        spectrum = np.abs(np.fft.rfft(locked)) * 2.0 / period / np.sqrt(2.0)
        print(
            f"   {law} ({driver} creep): RMS {_rms(r[keep]):.4f} = phase-locked {_rms(locked):.4f}"
            f" (1f {spectrum[1]:.4f}, 2f {spectrum[2]:.4f}, 3f {spectrum[3]:.4f})"
            f" + slow {_rms(slow[inner]):.4f} + rest {_rms((rest - slow)[inner]):.4f}"
        )

    print("\n2. the validation run predicted (fitted on the identification run), stretch by stretch")
    keep_v = settled_rows(valid, SKIP_S)
    t = np.concatenate(
        [
            e.t_start_s + np.linspace(0.0, e.duration_s, int(c))
            for e, c in zip(valid.experiments, valid.counts, strict=True)
        ]
    )
    for (law, driver), fit in fits.items():
        err = np.zeros(keep_v.size)
        err[keep_v] = _error(valid, fit.params, keep_v)
        print(
            f"   {law} ({driver} creep): whole run {_rms(err[keep_v]):.4f} ({_rms(err[keep_v]) / floor:.2f}x)"
        )
        for name, a, b in STRETCHES:
            sel = keep_v & (t >= a) & (t < b)
            e = err[sel]
            print(
                f"      {a:4.0f}-{b:3.0f} s {name:<28} RMS {_rms(e):.4f}  mean {e.mean():+.4f}"
                f"  about the mean {float(e.std()):.4f}"
            )

    print(
        "\n3. nested loops in the training data: one experiment of the validation run fitted,"
        " the other predicted"
    )
    exp_of_row = np.repeat(np.arange(valid.n_experiments), valid.counts)
    for law, driver in members:
        for k, name in enumerate(("open loop", "compensated")):
            train = np.arange(valid.n_experiments) == k
            fit = fit_family(
                valid, law, plays=args.plays, skip_s=SKIP_S, creep_driver=driver, fit_lag=False, train=train
            )
            test = keep_v & ~train[exp_of_row]
            e = _error(valid, fit.params, test)
            print(
                f"   {law} ({driver} creep) fitted on the {name} part: training {fit.rms_um:.4f}"
                f" ({fit.rms_um / floor:.2f}x), the other part {_rms(e):.4f} ({_rms(e) / floor:.2f}x)"
            )

    print(
        "\n4. the identification run's unknown history: the stage rested at 0 V before it"
        " (not at its first voltage)"
    )
    _, ident0 = _prepare("identification.csv", 1, 1.0, rest_voltage_v=0.0)
    for law, driver in members:
        fit = fit_family(ident0, law, plays=args.plays, skip_s=SKIP_S, creep_driver=driver, fit_lag=False)
        e = _error(valid, fit.params, keep_v)
        print(
            f"   {law} ({driver} creep): identification {fit.rms_um:.4f}, validation {_rms(e):.4f}"
            f" ({_rms(e) / floor:.2f}x)"
        )

    print("\n5. a loop centre driven by the cycling: low-passed |dV/dt| (tau 0.3-30 s) on the residual")
    keep = settled_rows(ident, SKIP_S)
    fi = _activity(ident, keep)
    fv = _activity(valid, keep_v)
    for (law, driver), fit in fits.items():
        ei = _centred(ident, _error(ident, fit.params, np.ones(keep.size, dtype=bool))[:, None], keep)[:, 0]
        ev = np.zeros(keep_v.size)
        ev[keep_v] = _error(valid, fit.params, keep_v)
        w, *_ = np.linalg.lstsq(fi[keep], -ei[keep], rcond=None)
        carried = _centred(valid, (ev + fv @ w)[:, None], keep_v)[:, 0]
        w_v, *_ = np.linalg.lstsq(fv[keep_v], -ev[keep_v], rcond=None)
        bound = _centred(valid, (ev + fv @ w_v)[:, None], keep_v)[:, 0]
        print(
            f"   {law} ({driver} creep): identification {_rms(ei[keep]):.4f}"
            f" -> {_rms((ei + fi @ w)[keep]):.4f};"
            f" validation {_rms(ev[keep_v]):.4f} -> {_rms(carried[keep_v]):.4f}"
            f" ({_rms(carried[keep_v]) / floor:.2f}x); fitted on the validation run itself"
            f" {_rms(bound[keep_v]):.4f} ({_rms(bound[keep_v]) / floor:.2f}x)"
        )

    print("\n6. what a law can fit at all: fitted on the validation run itself, and a full Preisach density")
    for law in ("prandtl-ishlinskii", "generalised-play", "coleman-hodgdon", "bouc-wen"):
        for driver in ("position", "voltage"):
            try:
                fit = fit_family(
                    valid, law, plays=args.plays, skip_s=SKIP_S, creep_driver=driver, fit_lag=False
                )
            except CalibrationError as exc:
                print(f"   {law} ({driver} creep) fitted on the validation run: failed ({exc})")
                continue
            ratio = fit.rms_um / floor
            print(f"   {law} ({driver} creep) fitted on the validation run: {fit.rms_um:.4f} ({ratio:.2f}x)")
    lo = min(float(ident.grid_voltage_v.min()), float(valid.grid_voltage_v.min())) - 0.05
    hi = max(float(ident.grid_voltage_v.max()), float(valid.grid_voltage_v.max())) + 0.05
    xi, xv = _preisach_columns(ident, lo, hi), _preisach_columns(valid, lo, hi)
    keep_i = settled_rows(ident, SKIP_S)
    exp_i = np.repeat(np.arange(ident.n_experiments), ident.counts)
    exp_v = np.repeat(np.arange(valid.n_experiments), valid.counts)

    def with_offsets(x: F64, exp: NDArray[np.intp], n: int, shift: int) -> F64:
        ind = np.zeros((x.shape[0], n_offsets))
        ind[np.arange(x.shape[0]), exp + shift] = 1.0
        return np.column_stack([x, ind])

    n_offsets = ident.n_experiments + valid.n_experiments
    own = _ridge(with_offsets(xv, exp_v, valid.n_experiments, 0)[keep_v], valid.position_um[keep_v])
    own_rms = _scored(valid, with_offsets(xv, exp_v, valid.n_experiments, 0) @ own, keep_v)
    comp = keep_v & (exp_v == 1)
    both_x = np.vstack(
        [
            with_offsets(xi, exp_i, ident.n_experiments, 0)[keep_i],
            with_offsets(xv, exp_v, valid.n_experiments, ident.n_experiments)[comp],
        ]
    )
    both = _ridge(both_x, np.concatenate([ident.position_um[keep_i], valid.position_um[comp]]))
    n_cols = xv.shape[1]
    open_rows = keep_v & (exp_v == 0)
    nested = _scored(valid, xv @ both[:n_cols], open_rows)
    alone = _ridge(with_offsets(xi, exp_i, ident.n_experiments, 0)[keep_i], ident.position_um[keep_i])
    carried_rms = _scored(valid, xv @ alone[:n_cols], keep_v)
    print(
        f"   full Preisach density ({xv.shape[1] - 2 - len(PREISACH_TAUS_S)} relays) + voltage creep:"
        f" fitted on the validation run {own_rms:.4f} ({own_rms / floor:.2f}x);"
        f" fitted on the identification run and the compensated part, the open-loop part"
        f" {nested:.4f} ({nested / floor:.2f}x); fitted on the identification run alone, the"
        f" validation run {carried_rms:.4f} ({carried_rms / floor:.2f}x)"
    )
    _part7(valid, valid.position_um - with_offsets(xv, exp_v, valid.n_experiments, 0) @ own, keep_v)
    return 0


def _part7(data: DynamicCalibrationData, resid: F64, keep: NDArray[np.bool_]) -> None:
    """What the free Preisach density leaves on its own training run, by stretch and band."""
    print("\n7. what the full Preisach density leaves on the run it is fitted to, by stretch and band")
    dt = 0.005
    t = np.arange(resid.size) * dt
    for name, a, b in (
        ("open loop, full amplitude", 2.0, 16.0),
        ("open loop, rest", 20.5, 24.0),
        ("compensated, full amplitude", 61.0, 71.0),
        ("compensated, rest", 52.5, 56.0),
    ):
        r = resid[(t >= a) & (t < b) & keep]
        r = r - r.mean()
        f = np.fft.rfftfreq(r.size, dt)
        p = 2.0 * np.abs(np.fft.rfft(r)) ** 2 / r.size**2
        band = [
            float(np.sqrt(p[(f >= lo) & (f < hi)].sum()))
            for lo, hi in ((0.0, 5.0), (5.0, 30.0), (30.0, 101.0))
        ]
        lines = [float(np.sqrt(p[np.abs(f - fl) <= 0.3].sum())) for fl in (58.0, 100.0)]
        print(
            f"   {name:<28} {a:4.1f}-{b:4.1f} s  RMS {r.std():.4f}: below 5 Hz {band[0]:.4f}, 5-30 Hz"
            f" {band[1]:.4f}, above 30 Hz {band[2]:.4f}; lines 58 Hz {lines[0]:.4f}, 100 Hz {lines[1]:.4f}"
        )
    # the part locked to the 1 Hz drive (its mean over 7 cycles) carried to the next 7 and to 29-36 s
    per = round(1.0 / dt)
    cycles = [resid[round(s / dt) : round(s / dt) + 7 * per].reshape(7, per) for s in (2.0, 9.0, 29.0)]
    locked = cycles[0].mean(axis=0)
    for label, c in (("the next 7 cycles (9-16 s)", cycles[1]), ("7 cycles 27 s later (29-36 s)", cycles[2])):
        print(
            f"   the residual's mean cycle of 2-9 s subtracted from {label}: RMS {c.std():.4f} ->"
            f" {(c - locked).std():.4f}"
        )


if __name__ == "__main__":
    raise SystemExit(main())
