"""What the actuator model cannot describe, found model-free: switching, holds, lost sensitivity.

Three checks run on the measured data before (and independently of) the baseline fit:

* **switching** (polarization switching of a ferroelectric above its coercive voltage): on a
  voltage branch that moves one way, a piezo actuator's position moves one way too (the
  hysteresis model's branches are monotonic). A butterfly response (even in ``V``) turns
  back inside the branch at the coercive voltage. A branch whose binned position turns back by
  more than 10 % of its span (and 5x its noise) away from the reversals is switching; the
  voltage of the turn is reported. The actuator model does not apply there.
* **holds** (the voltage constant for at least :data:`HOLD_MIN_S`): after the step into a hold
  the position creeps by a log law ``c log10(1 + (t - t0)/tau0)`` (``tau0`` <= a tenth of the
  hold); a linear term on top of it is a drift. The drift is named when the straight line is
  needed (BIC falls by more than 10 with it, consistently signed over the holds) and its rate is
  significant; the held-out gain comes from a 2-fold split of every hold into interleaved blocks.
* **lost sensitivity**: the slope ``dx/dV`` of every experiment against those of the same
  voltage range before the largest excursion of the session; a loss of more than 10 % after it
  is a finding with its size (a ceramic partially depoled by a large cycle).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from piezod.audit.residuals import noise_floor
from piezod.fitstats import solve_linear
from piezod.recording import Experiment

F64 = NDArray[np.float64]

#: Shortest voltage hold analysed (s).
HOLD_MIN_S = 30.0
#: Fewest samples of a hold.
HOLD_MIN_SAMPLES = 200
#: Relative turn-back of a branch that counts as switching.
SWITCH_MIN_FRACTION = 0.1
#: Relative sensitivity loss after the largest excursion that is reported.
LOSS_MIN_FRACTION = 0.1


@dataclass(frozen=True)
class Switching:
    """Polarization switching found on the voltage branches.

    Attributes
    ----------
    onset_v
        The voltage of the turn nearest to 0 V (the coercive voltage reached), V.
    turn_fraction
        Largest turn-back over the branch span.
    experiments
        Labels of the experiments that switch.
    text
        One sentence for the report.
    """

    onset_v: float
    turn_fraction: float
    experiments: tuple[str, ...]
    text: str


@dataclass(frozen=True)
class HoldDrift:
    """A linear drift found in voltage holds.

    Attributes
    ----------
    rate_nm_per_s, rate_se_nm_per_s
        Weighted mean rate over the holds and its standard error.
    gain, gain_se
        Held-out RMS of the log law alone over the log law + line (2-fold interleaved blocks).
    bic_delta
        BIC change of the line added to the log law, summed over the holds.
    n_holds, seconds
        Holds used and their total duration.
    significant
        The drift is needed and significant.
    text
        Evidence.
    """

    rate_nm_per_s: float
    rate_se_nm_per_s: float
    gain: float
    gain_se: float
    bic_delta: float
    n_holds: int
    seconds: float
    significant: bool
    text: str


@dataclass(frozen=True)
class SensitivityLoss:
    """Sensitivity lost after the largest excursion of the session.

    Attributes
    ----------
    loss_pct
        Relative loss of ``dx/dV`` (per cent, positive = lost).
    after
        Label of the experiment with the largest excursion.
    peak_v
        Its largest ``|V|``.
    text
        Evidence.
    """

    loss_pct: float
    after: str
    peak_v: float
    text: str


@dataclass(frozen=True)
class Outside:
    """Everything the model-free checks found."""

    switching: Switching | None = None
    drift: HoldDrift | None = None
    loss: SensitivityLoss | None = None
    holds: tuple[tuple[str, int, int], ...] = field(default=())


# ------------------------------------------------------------------------------------------ switching


def _branches(v: F64) -> list[tuple[int, int, int]]:
    """Monotonic voltage runs ``(start, stop, sign)`` (constant stretches join the run before)."""
    dv = np.diff(v)
    span = float(np.ptp(v))
    if span <= 0 or v.size < 3:
        return []
    s = np.sign(np.where(np.abs(dv) > 1e-9 * span, dv, 0.0))
    nz = np.flatnonzero(s)
    if nz.size == 0:
        return []
    filled = s.copy()
    # Forward-fill zeros with the last direction.
    idx = np.where(s != 0, np.arange(s.size), 0)
    np.maximum.accumulate(idx, out=idx)
    filled = s[idx]
    filled[: nz[0]] = s[nz[0]]
    cuts = np.flatnonzero(np.diff(filled) != 0) + 1
    edges = np.concatenate(([0], cuts, [filled.size]))
    return [(int(a), int(b) + 1, int(filled[a])) for a, b in itertools.pairwise(edges)]


def switching(experiments: Sequence[Experiment], max_bins: int = 64) -> Switching | None:
    """Polarization switching: a position that turns back on a monotonic voltage branch."""
    orient = []
    for e in experiments:
        v, x = np.asarray(e.voltage_v, float), np.asarray(e.position_um, float)
        if np.ptp(v) > 0 and np.ptp(x) > 0:
            c = np.corrcoef(v, x)[0, 1]
            if math.isfinite(c):
                orient.append(c * np.ptp(v))
    if not orient:
        return None
    sign = 1.0 if float(np.sum(orient)) >= 0 else -1.0
    hits: list[tuple[float, float, str, bool]] = []
    for e in experiments:
        v, x = np.asarray(e.voltage_v, float), np.asarray(e.position_um, float)
        span_v = float(np.ptp(v))
        if span_v <= 0:
            continue
        sigma = noise_floor(x)
        for a, b, s in _branches(v):
            vb, xb = v[a:b], x[a:b]
            lo, hi = float(vb.min()), float(vb.max())
            bins = min(max_bins, vb.size // 8)
            if hi - lo < 0.5 * span_v or bins < 12:
                continue
            # Away from the reversals (lag, ringing and the turning point itself).
            inner = (vb > lo + 0.1 * (hi - lo)) & (vb < hi - 0.1 * (hi - lo))
            edges = np.linspace(lo + 0.1 * (hi - lo), hi - 0.1 * (hi - lo), bins + 1)
            k = np.clip(np.searchsorted(edges, vb[inner]) - 1, 0, bins - 1)
            cnt = np.bincount(k, minlength=bins)
            if np.any(cnt == 0):
                continue
            m = np.bincount(k, weights=xb[inner], minlength=bins) / cnt
            centres = 0.5 * (edges[:-1] + edges[1:])
            if s < 0:
                m, centres, cnt = m[::-1], centres[::-1], cnt[::-1]
            y = sign * s * m  # rising along the branch for an actuator (either direction)
            full = float(np.ptp(m))
            if full <= 0:
                continue
            peak = np.maximum.accumulate(y)
            drop = peak - y
            j = int(np.argmax(drop))
            depth = float(drop[j])
            err = sigma / math.sqrt(float(cnt.min())) if math.isfinite(sigma) else 0.0
            if depth > SWITCH_MIN_FRACTION * full and depth > 5.0 * err + 1e-12:
                i = int(np.argmax(y[: j + 1]))
                # The turn: where the position reverses its direction on this branch; a branch
                # that runs the wrong way from its start has a reversed loop orientation.
                reversed_ = i == 0 and depth > 0.9 * full
                hits.append((float(centres[i]), depth / full, e.label, reversed_))
    if not hits:
        return None
    turns = [h for h in hits if not h[3]]
    onset = min(turns, key=lambda h: abs(h[0]))[0] if turns else math.nan
    frac = max(h[1] for h in hits)
    labels = tuple(dict.fromkeys(h[2] for h in hits))
    rev = tuple(dict.fromkeys(h[2] for h in hits if h[3]))
    parts = []
    if turns:
        parts.append(
            f"the position turns back on a monotonic voltage branch (by up to {100 * frac:.3g} % of the "
            f"branch's travel) from about {onset:+.4g} V on: a butterfly response, even in V, as from "
            "polarization switching above the coercive voltage"
        )
    if rev:
        parts.append(
            f"the loop orientation is reversed in {', '.join(rev[:4])}{', ...' if len(rev) > 4 else ''}"
        )
    text = (
        "; ".join(parts)
        + f"; the actuator model does not apply there ({len(labels)} experiment(s): "
        + f"{', '.join(labels[:4])}{', ...' if len(labels) > 4 else ''})"
    )
    return Switching(onset, frac, labels, text)


# ------------------------------------------------------------------------------------------ holds


def holds(e: Experiment) -> list[tuple[int, int]]:
    """Sample ranges ``[a, b)`` where the voltage stays constant for at least :data:`HOLD_MIN_S`."""
    v = np.asarray(e.voltage_v, float)
    t = np.asarray(e.t_s, float)
    if v.size < HOLD_MIN_SAMPLES:
        return []
    span = float(np.ptp(v))
    # White noise of the recorded voltage (MAD of second differences of the raw samples): a noisy
    # monitor still holds. The smoothed voltage below steps by sqrt(2) noise / w per sample; the
    # monitor's resolution (1e-4 of the level) bounds the tolerance from below, so that a
    # recording that is one hold (its span all noise or quantisation) is a hold.
    d2 = np.diff(v, 2)
    noise = float(1.4826 * np.median(np.abs(d2 - np.median(d2))) / math.sqrt(6.0)) if d2.size else 0.0
    w = 9
    v = np.convolve(np.pad(v, w // 2, mode="edge"), np.ones(w) / w, mode="valid")
    tol = max(2e-3 * span, 6.0 * math.sqrt(2.0) * noise / w, 1e-4 * max(float(np.max(np.abs(v))), 1.0))
    still = np.abs(np.diff(v)) <= tol
    out: list[tuple[int, int]] = []
    edges = np.flatnonzero(np.diff(np.concatenate(([0], still.astype(np.int8), [0]))))
    for a0, b0 in zip(edges[::2], edges[1::2], strict=True):
        a0, stop0 = int(a0), int(b0) + 1
        if stop0 - a0 < HOLD_MIN_SAMPLES:
            continue
        # A slow ramp into the hold moves by less than tol per sample too: keep the longest
        # stretch at the level the run ends at (within 2 tol).
        seg = v[a0:stop0]
        level = float(np.median(seg[-max(HOLD_MIN_SAMPLES // 2, 1) :]))
        near = np.abs(seg - level) <= 2.0 * tol
        e2 = np.flatnonzero(np.diff(np.concatenate(([0], near.astype(np.int8), [0]))))
        if e2.size == 0:
            continue
        lens = e2[1::2] - e2[::2]
        j = int(np.argmax(lens))
        a, stop = a0 + int(e2[2 * j]) + w, a0 + int(e2[2 * j + 1])
        if stop - a < HOLD_MIN_SAMPLES or t[stop - 1] - t[a] < HOLD_MIN_S:
            continue
        out.append((a, stop))
    return out


#: Exponents of the creep law in a hold: ``((1 + t/tau0)^beta - 1) / beta`` (beta = 0: log).
#: PZT creep follows a log or a weak power law (beta ~ 0.01-0.1); a drift must be needed on
#: top of the best of them, or the law's departure from a log would be taken for a drift.
CREEP_BETAS: tuple[float, ...] = (0.0, 0.05, 0.1, 0.2)
#: A drift must exceed this fraction of the creep's own rate at the end of the hold.
CREEP_RATE_FRACTION = 0.5


def _log_basis(tt: F64, shape: tuple[float, float]) -> F64:
    tau0, beta = shape
    u = np.log1p(tt / tau0)
    out: F64 = u / math.log(10.0) if beta == 0.0 else np.expm1(beta * u) / (beta * math.log(10.0))
    return out


def _hold_fit(tt: F64, x: F64, with_line: bool, taus: F64) -> tuple[float, F64, tuple[float, float]]:
    """Best ``a + c creep(t; tau0, beta) [+ r t]`` over the ``tau0`` x beta grid: (rss, coef, shape)."""
    best: tuple[float, F64, tuple[float, float]] | None = None
    for tau in taus:
        for beta in CREEP_BETAS:
            shape = (float(tau), beta)
            cols = [np.ones_like(tt), _log_basis(tt, shape)]
            if with_line:
                cols.append(tt)
            a = np.column_stack(cols)
            coef, _ = solve_linear(a, x)
            r = x - a @ coef
            rss = float(r @ r)
            if best is None or rss < best[0]:
                best = (rss, coef, shape)
    assert best is not None
    return best


def hold_drift(experiments: Sequence[Experiment]) -> tuple[HoldDrift | None, list[tuple[str, int, int]]]:
    """A linear drift in the voltage holds, separated from the log creep after the step."""
    found: list[tuple[str, int, int]] = []
    rates, ses, bics = [], [], []
    ss_log: list[F64] = []
    ss_line: list[F64] = []
    creep_end: list[float] = []
    seconds = 0.0
    for e in experiments:
        t = np.asarray(e.t_s, float)
        x = np.asarray(e.position_um, float)
        for a, b in holds(e):
            found.append((e.label, a, b))
            tt = t[a:b] - t[a]
            xx = x[a:b]
            dur = float(tt[-1])
            seconds += dur
            dt = float(np.median(np.diff(tt)))
            taus = np.geomspace(max(dt, 1e-3), max(0.1 * dur, 2.0 * dt), 12)
            rss0, _, _ = _hold_fit(tt, xx, False, taus)
            rss1, coef, tau = _hold_fit(tt, xx, True, taus)
            n = xx.size
            # The creep's own rate at the end of the hold: a line much slower than it cannot be
            # told from the creep law's error (the creep of earlier voltage changes, a spread of
            # relaxation times that is neither log nor power law).
            tau0, beta = tau
            creep_end.append(
                abs(float(coef[1])) * (1.0 + dur / tau0) ** (beta - 1.0) / (tau0 * math.log(10.0)) * 1e3
            )
            # Correlated noise: the effective number of independent samples from the residual's
            # lag-1 autocorrelation, so that the BIC and the standard error are not overconfident.
            cols = np.column_stack((np.ones_like(tt), _log_basis(tt, tau), tt))
            r = xx - cols @ coef
            rho = float(np.corrcoef(r[:-1], r[1:])[0, 1]) if n > 3 and np.std(r) > 0 else 0.0
            rho = min(max(rho, 0.0), 0.999)
            n_eff = max(n * (1.0 - rho) / (1.0 + rho), 4.0)
            bics.append(n_eff * math.log(max(rss1, 1e-300) / max(rss0, 1e-300)) + math.log(n_eff))
            cov = np.linalg.pinv(cols.T @ cols) * rss1 / max(n - 3, 1)
            se = math.sqrt(max(float(cov[2, 2]), 0.0) * n / n_eff)
            rates.append(float(coef[2]) * 1e3)
            ses.append(se * 1e3)
            # Held out: fit on even blocks, predict odd ones, and vice versa; only blocks with
            # training data on both sides (the first block would test the log law's
            # extrapolation back to the fast creep right after the step, not the line).
            num = np.arange(n) * 20 // n
            blk = num % 2
            inner = (num > 0) & (num < 19)
            for g in (0, 1):
                tr, te = blk != g, (blk == g) & inner
                for with_line, acc in ((False, ss_log), (True, ss_line)):
                    _, c, tau_g = _hold_fit(tt[tr], xx[tr], with_line, taus)
                    basis = [np.ones(int(te.sum())), _log_basis(tt[te], tau_g)]
                    if with_line:
                        basis.append(tt[te])
                    res = xx[te] - np.column_stack(basis) @ c
                    acc.append(res)
    if not rates:
        return None, found
    w = 1.0 / np.maximum(np.asarray(ses), 1e-12) ** 2
    rate = float(np.sum(w * np.asarray(rates)) / np.sum(w))
    rate_se = float(1.0 / math.sqrt(float(np.sum(w))))
    r_log = np.concatenate(ss_log)
    r_line = np.concatenate(ss_line)
    gain = math.sqrt(float(r_log @ r_log) / max(float(r_line @ r_line), 1e-300))
    # Block jackknife of the gain over 10 contiguous blocks.
    k = 10
    e_ = (np.arange(k + 1) * r_log.size) // k
    sb = np.add.reduceat(r_log**2, e_[:-1])
    sa = np.add.reduceat(r_line**2, e_[:-1])
    loo = np.sqrt((sb.sum() - sb) / np.maximum(sa.sum() - sa, 1e-300))
    gain_se = math.sqrt((k - 1) / k * float(np.sum((loo - loo.mean()) ** 2)))
    bic = float(np.sum(bics))
    same_sign = len({np.sign(r) for r in rates}) == 1
    creep_rate = float(np.median(creep_end))
    significant = (
        bic < -10.0
        and abs(rate) > 3.0 * rate_se
        and abs(rate) > CREEP_RATE_FRACTION * creep_rate
        and same_sign
        and gain - 1.0 > 2.0 * gain_se
    )
    text = (
        f"in {len(rates)} voltage hold(s) ({seconds:.4g} s) the position moves on linearly after the log "
        f"creep of the step: {rate:+.3g} +- {rate_se:.2g} nm/s (a straight line on top of "
        f"the creep law c ((1 + t/tau0)^beta - 1)/beta, beta 0 (log) to 0.2: BIC {bic:+.4g}, "
        f"held-out gain {gain:.3g} +- {gain_se:.2g} on interleaved "
        f"blocks of the holds; the creep itself moves at {creep_rate:.3g} nm/s at the end of the hold)"
    )
    return HoldDrift(rate, rate_se, gain, gain_se, bic, len(rates), seconds, significant, text), found


# ------------------------------------------------------------------------------------------ sensitivity


def sensitivity_loss(experiments: Sequence[Experiment]) -> SensitivityLoss | None:
    """Sensitivity lost after the largest excursion: ``dx/dV`` of the same range before and after it."""
    rows = []
    for e in experiments:
        v, x = np.asarray(e.voltage_v, float), np.asarray(e.position_um, float)
        span = float(np.ptp(v))
        if span <= 0 or v.size < 16:
            continue
        slope = float(np.polyfit(v, x, 1)[0])
        rows.append((e.label, float(np.max(np.abs(v))), span, slope))
    if len(rows) < 3:
        return None
    peaks = np.array([r[1] for r in rows])
    k = int(np.argmax(peaks))
    if k == 0 or k == len(rows) - 1:
        return None
    big = peaks[k]
    others = [i for i in range(len(rows)) if peaks[i] < 0.8 * big]
    if not others:
        return None
    best: tuple[float, int, int] | None = None
    for i in (i for i in others if i < k):
        for j in (j for j in others if j > k):
            if abs(rows[i][2] - rows[j][2]) <= 0.1 * max(rows[i][2], rows[j][2]):
                d = abs(rows[i][2] - rows[j][2])
                if best is None or d < best[0]:
                    best = (d, i, j)
    if best is None:
        return None
    _, i, j = best
    s0, s1 = rows[i][3], rows[j][3]
    loss = 1.0 if s0 == 0 else 1.0 - s1 / s0
    if loss < LOSS_MIN_FRACTION:
        return None
    text = (
        f"after {rows[k][0]} (up to {big:.4g} V) the sensitivity dx/dV of a {rows[j][2]:.4g} V scan "
        f"is {100 * loss:.3g} % below that of the same scan before it ({rows[i][0]} -> {rows[j][0]}): "
        "the large excursion cost sensitivity (depoling); a per-session gain hides it"
    )
    return SensitivityLoss(100.0 * loss, rows[k][0], big, text)


def check(experiments: Sequence[Experiment]) -> Outside:
    """Run the model-free checks on the training experiments."""
    drift, found = hold_drift(experiments)
    return Outside(
        switching=switching(experiments),
        drift=drift,
        loss=sensitivity_loss(experiments),
        holds=tuple(found),
    )
