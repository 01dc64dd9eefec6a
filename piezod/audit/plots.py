"""Plots of an audit (matplotlib, optional extra, headless Agg backend).

:func:`write_plots` writes into a directory:

* ``summary.png``    residual of the fitted and of the held-out data before / after, residual
  against voltage, held-out gain per candidate;
* ``residuals.png``  baseline and final residual against session time, with the noise floor;
* ``loops.png``      measured loops with the baseline and the final model, residual against voltage;
* ``gains.png``      held-out gain and BIC change of every candidate in every round;
* ``structure.png``  residual binned against voltage, voltage rate and travel since the last
  reversal; per-experiment sensitivity error against time, offset, range and line rate; loop
  opening against line rate; residual spectra.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from piezod.audit.decide import AuditResult
from piezod.errors import PiezodError

F64 = NDArray[np.float64]


def _pyplot() -> Any:
    try:
        import matplotlib
    except ImportError as exc:  # pragma: no cover - depends on the installation
        raise PiezodError("--plots needs matplotlib: pip install 'spm-piezod[plots]'") from exc
    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _full(result: AuditResult, r: F64) -> F64:
    out = np.full(result.data.n, np.nan)
    out[result.data.fit_mask] = r
    return out


def write_plots(result: AuditResult, directory: str | os.PathLike[str]) -> list[Path]:
    """Write the audit's plots into ``directory`` (created); returns the files written."""
    plt = _pyplot()
    d = Path(directory)
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PiezodError(f"cannot create the plot directory {d}: {exc.strerror or exc}") from exc
    written = []
    for name, fn in (
        ("summary.png", _summary),
        ("residuals.png", _residuals),
        ("loops.png", _loops),
        ("gains.png", _gains),
        ("structure.png", _structure),
    ):
        fig = fn(plt, result)
        path = d / name
        fig.savefig(path, dpi=80)
        plt.close(fig)
        written.append(path)
    return written


def _label(result: AuditResult) -> str:
    eff = result.final_fit.model.effects
    return "baseline + " + " + ".join(eff) if eff else "baseline"


def _summary(plt: Any, result: AuditResult) -> Any:
    data = result.data
    fig, ax = plt.subplots(2, 2, figsize=(11, 7))
    before = _full(result, result.base_fit.residual)
    after = _full(result, result.final_fit.residual)
    label = _label(result)
    a = ax[0, 0]
    a.plot(data.t_s, before, ",", color="tab:red", alpha=0.6, rasterized=True, label="baseline")
    a.plot(data.t_s, after, ",", color="tab:blue", alpha=0.6, rasterized=True, label=label)
    a.set_xlabel("session time (s)")
    a.set_ylabel("residual (um)")
    a.set_title("fitted data: residual against time", fontsize=9)
    a.legend(markerscale=25, fontsize=7, loc="upper right")
    a = ax[0, 1]
    ho_data = result.val_geo.data if result.val_geo is not None else data
    for ho, color in ((result.base_heldout, "tab:red"), (result.final_heldout, "tab:blue")):
        a.plot(ho_data.t_s[ho.rows], ho.residual, ",", color=color, alpha=0.6, rasterized=True)
    a.set_xlabel("time (s)")
    a.set_title(
        f"held-out data ({result.heldout_method}): RMS {result.base_heldout.rms_um:.3g} -> "
        f"{result.final_heldout.rms_um:.3g} um",
        fontsize=9,
    )
    a = ax[1, 0]
    a.plot(data.voltage_v, before, ",", color="tab:red", alpha=0.6, rasterized=True)
    a.plot(data.voltage_v, after, ",", color="tab:blue", alpha=0.6, rasterized=True)
    a.set_xlabel("voltage (V)")
    a.set_ylabel("residual (um)")
    a.set_title("fitted data: residual against voltage", fontsize=9)
    _gain_bars(ax[1, 1], result, rounds=1)
    fig.suptitle(f"piezod audit: cause {result.cause}", fontsize=11)
    fig.tight_layout()
    return fig


def _residuals(plt: Any, result: AuditResult) -> Any:
    data = result.data
    fig, ax = plt.subplots(2, 1, figsize=(12, 6), sharex=True, sharey=True)
    floor = result.noise_floor_um
    for a, r, title in (
        (ax[0], result.base_fit.residual, f"baseline, rms {result.base_fit.rms_um:.4g} um"),
        (ax[1], result.final_fit.residual, f"{_label(result)}, rms {result.final_fit.rms_um:.4g} um"),
    ):
        full = _full(result, r)
        for i in range(data.n_experiments):
            sl = data.slice(i)
            a.plot(data.t_s[sl], full[sl], lw=0.4)
        if math.isfinite(floor):
            for sgn in (-2.0, 2.0):
                a.axhline(sgn * floor, color="k", lw=0.6, ls="--")
        a.set_title(title + "  (dashed: +-2 x noise floor)", fontsize=9)
        a.set_ylabel("residual (um)")
    ax[1].set_xlabel("session time (s)")
    fig.tight_layout()
    return fig


def _pick(result: AuditResult, k: int = 4) -> list[int]:
    data = result.data
    rms = np.array([p["rms_um"] for p in result.base_structure.per_experiment], dtype=float)
    rms = np.where(np.isfinite(rms), rms, -1.0)
    f = np.array([e.frequency_hz if math.isfinite(e.frequency_hz) else 0.0 for e in data.info])
    picks = [int(np.argmax(rms)), int(np.argmax(f)), int(np.argmin(np.where(f > 0, f, np.inf)))]
    picks.append(int(np.argmax([e.range_v for e in data.info])))
    out: list[int] = []
    for p in picks:
        if p not in out:
            out.append(p)
    return out[:k]


def _loops(plt: Any, result: AuditResult) -> Any:
    data = result.data
    idx = _pick(result)
    fig, ax = plt.subplots(2, len(idx), figsize=(3.6 * len(idx), 6.5), squeeze=False)
    before = _full(result, result.base_fit.residual)
    after = _full(result, result.final_fit.residual)
    for j, i in enumerate(idx):
        sl = data.slice(i)
        v = data.voltage_v[sl]
        x = data.position_um[sl]
        a = ax[0, j]
        a.plot(v, x, ",", color="0.4", label="measured", rasterized=True)
        a.plot(v, x - before[sl], lw=0.6, color="tab:red", label="baseline")
        a.plot(v, x - after[sl], lw=0.6, color="tab:blue", ls="--", label=_label(result))
        e = data.info[i]
        f = f"{e.frequency_hz:.3g} Hz" if math.isfinite(e.frequency_hz) else e.kind
        a.set_title(f"{e.label[-24:]}\n{e.range_v:.0f} V p-p, {f}", fontsize=8)
        a.set_xlabel("voltage (V)")
        b = ax[1, j]
        up = data.direction[sl] > 0
        for mask, c_before, c_after in ((up, "tab:red", "tab:blue"), (~up, "tab:orange", "tab:cyan")):
            b.plot(v[mask], before[sl][mask], ",", color=c_before, rasterized=True)
            b.plot(v[mask], after[sl][mask], ",", color=c_after, rasterized=True)
        b.set_xlabel("voltage (V)")
    ax[0, 0].set_ylabel("position (um)")
    ax[1, 0].set_ylabel("residual (um); red/orange baseline, blue/cyan final (trace/retrace)")
    ax[0, 0].legend(fontsize=7, markerscale=10)
    fig.tight_layout()
    return fig


def _gain_bars(a: Any, result: AuditResult, rounds: int | None = None) -> None:
    rr = result.rounds if rounds is None else result.rounds[:rounds]
    effects = [c.effect for c in result.rounds[0]] if result.rounds else []
    width = 0.8 / max(len(rr), 1)
    for k, rnd in enumerate(rr):
        g = {c.effect: c.gain for c in rnd if c.fit is not None}
        vals = [g.get(e, math.nan) for e in effects]
        pos = np.arange(len(effects)) + k * width
        colors = ["tab:green" if any(c.effect == e and c.eligible for c in rnd) else "0.6" for e in effects]
        a.bar(
            pos,
            np.nan_to_num(np.array(vals, dtype=float), nan=0.0),
            width=width,
            color=colors,
            edgecolor="k",
            lw=0.3,
            label=f"round {k + 1}",
        )
    a.axhline(1.0, color="k", lw=0.6)
    a.axhline(result.options.gain_min, color="tab:green", lw=0.6, ls="--")
    a.set_yscale("log")
    from matplotlib.ticker import LogLocator, NullFormatter, ScalarFormatter

    a.yaxis.set_major_locator(LogLocator(base=10.0, subs=(1.0, 1.2, 1.5, 2.0, 3.0, 5.0)))
    a.yaxis.set_major_formatter(ScalarFormatter())
    a.yaxis.set_minor_formatter(NullFormatter())
    a.set_xticks(np.arange(len(effects)) + 0.4 - width / 2)
    a.set_xticklabels(effects, rotation=45, fontsize=8)
    a.set_ylabel("held-out gain (RMS before / after)")
    a.set_title("held-out gain per candidate (green: eligible)", fontsize=9)


def _gains(plt: Any, result: AuditResult) -> Any:
    fig, ax = plt.subplots(1, 2, figsize=(12, 4))
    _gain_bars(ax[0], result)
    effects = [c.effect for c in result.rounds[0]] if result.rounds else []
    for k, rnd in enumerate(result.rounds):
        b = {c.effect: c.bic_delta for c in rnd if c.fit is not None}
        vals = np.array([b.get(e, math.nan) for e in effects], dtype=float)
        ax[1].plot(np.arange(len(effects)), -vals, "o-", label=f"round {k + 1}")
    ax[1].axhline(result.options.bic_min, color="tab:green", lw=0.6, ls="--")
    ax[1].set_yscale("symlog")
    ax[1].set_xticks(np.arange(len(effects)))
    ax[1].set_xticklabels(effects, rotation=45, fontsize=8)
    ax[1].set_ylabel("BIC decrease")
    ax[1].legend(fontsize=8)
    fig.tight_layout()
    return fig


def _structure(plt: Any, result: AuditResult) -> Any:
    fig, ax = plt.subplots(3, 3, figsize=(13, 10))
    for s, color, name in (
        (result.base_structure, "tab:red", "baseline"),
        (result.final_structure, "tab:blue", "final"),
    ):
        for a, key, xl in (
            (ax[0, 0], "voltage_v", "voltage (V)"),
            (ax[0, 1], "voltage_rate_v_per_s", "voltage rate (V/s)"),
            (ax[0, 2], "since_reversal_v", "voltage since last reversal (V)"),
        ):
            bn = s.bins[key]
            a.plot(bn["centre"], bn["mean_um"], "o-", color=color, ms=3, label=f"{name} mean")
            a.plot(bn["centre"], bn["rms_um"], "s:", color=color, ms=3, label=f"{name} rms")
            a.set_xlabel(xl)
            a.set_ylabel("residual (um)")
        per = s.per_experiment
        ge = np.array([p["gain_error_pct"] for p in per], dtype=float)
        for a, key, xl in (
            (ax[1, 0], "t_mid_s", "session time (s)"),
            (ax[1, 1], "offset_v", "scan offset (V)"),
            (ax[1, 2], "range_v", "range (V p-p)"),
        ):
            xv = np.array([p[key] for p in per], dtype=float)
            a.plot(xv, ge, "o", color=color, ms=3, label=name)
            a.set_xlabel(xl)
            a.set_ylabel("sensitivity error (%)")
        f = np.array([p["frequency_hz"] for p in per], dtype=float)
        ax[2, 0].plot(f, ge, "o", color=color, ms=3, label=name)
        op = np.array([p["opening_error_um"] for p in per], dtype=float)
        ax[2, 1].plot(f, op, "o", color=color, ms=3, label=name)
    for a in (ax[2, 0], ax[2, 1]):
        if np.any(np.isfinite([e.frequency_hz for e in result.data.info])):
            a.set_xscale("log")
        a.set_xlabel("line rate (Hz)")
    ax[2, 0].set_ylabel("sensitivity error (%)")
    ax[2, 1].set_ylabel("loop-opening error (um)")
    from piezod.audit.residuals import spectrum

    for r, color, name in (
        (result.base_fit.residual, "tab:red", "baseline"),
        (result.final_fit.residual, "tab:blue", "final"),
    ):
        fr, amp = spectrum(result.data, result.data.fit_mask, r)
        if fr.size:
            ax[2, 2].loglog(fr, amp, color=color, lw=0.8, label=name)
    ax[2, 2].set_xlabel("frequency (Hz)")
    ax[2, 2].set_ylabel("residual amplitude (um/sqrt Hz)")
    for a in ax.ravel():
        a.legend(fontsize=6)
    fig.tight_layout()
    return fig
