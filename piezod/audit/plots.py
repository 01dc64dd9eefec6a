"""Plots of an audit (matplotlib, optional extra, headless Agg backend).

:func:`write_plots` writes into a directory:

* ``summary.png``    residual of the fitted and of the held-out data before / after, residual
  against voltage, held-out gain per candidate;
* ``residuals.png``  baseline and final residual against session time, with the noise floor;
* ``loops.png``      measured loops with the baseline and the final model, residual against voltage;
* ``gains.png``      held-out gain and BIC change of every candidate in every round;
* ``prediction.png`` measured position against the model's position, and the deviation;
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
        ("prediction.png", _prediction),
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
    a.set_ylabel("held-out residual (um)")
    a.plot([], [], "s", color="tab:red", label="baseline")
    a.plot([], [], "s", color="tab:blue", label=label)
    a.legend(fontsize=7, loc="upper right")
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


def _loops(plt: Any, result: AuditResult, max_panels: int = 16) -> Any:
    data = result.data
    n = data.n_experiments
    idx = (
        list(range(n)) if n <= max_panels else np.linspace(0, n - 1, max_panels).round().astype(int).tolist()
    )
    cols = min(4, len(idx))
    rows = math.ceil(len(idx) / cols)
    # At least 5 in wide: the title of a one-panel figure must fit.
    fig, ax = plt.subplots(rows, cols, figsize=(max(3.4 * cols + 0.8, 5.0), 2.9 * rows + 0.9), squeeze=False)
    before = _full(result, result.base_fit.residual)
    after = _full(result, result.final_fit.residual)
    for j, i in enumerate(idx):
        sl = data.slice(i)
        v = data.voltage_v[sl]
        x = data.position_um[sl]
        a = ax[j // cols, j % cols]
        a.plot(v, x, ",", color="0.3", label="measured", rasterized=True)
        a.plot(v, x - before[sl], lw=0.7, color="tab:red", label="baseline")
        if result.findings:
            a.plot(v, x - after[sl], lw=0.7, color="tab:blue", ls="--", label=_label(result))
        e = data.info[i]
        f = f"{e.frequency_hz:.3g} Hz" if math.isfinite(e.frequency_hz) else e.kind
        name = e.label if len(e.label) <= 28 else e.label[:12] + "..." + e.label[-13:]
        a.set_title(f"{name}\n{e.v_min:.4g} to {e.v_max:.4g} V, {f}", fontsize=8)
        a.tick_params(labelsize=7)
    for j in range(len(idx), rows * cols):
        ax[j // cols, j % cols].set_visible(False)
    ax[0, 0].legend(fontsize=7, markerscale=10)
    fig.supxlabel("voltage (V)")
    fig.supylabel("position (um)")
    shown = (
        ("the only experiment" if n == 1 else f"all {n} experiments")
        if len(idx) == n
        else f"{len(idx)} of {n} experiments (evenly spaced)"
    )
    fig.suptitle(f"measured loops and the fitted models,\n{shown}", fontsize=10)
    fig.tight_layout()
    return fig


def _status(result: AuditResult, rnd: int, c: Any) -> tuple[str, str]:
    """Colour and legend label of a candidate in round ``rnd`` (0-based), as the decision treats it."""
    chosen = [f.effect for f in result.findings if f.round == rnd + 1]
    if c.effect in chosen:
        return "tab:green", "finding (joins the model)"
    if c.eligible:
        return "#b7e4b0", "eligible, smaller gain"
    if c.implausible:
        return "tab:red", "implausible magnitude"
    return "0.7", "not eligible"


def _gain_bars(a: Any, result: AuditResult, rounds: int | None = None) -> None:
    rr = result.rounds if rounds is None else result.rounds[:rounds]
    effects = [c.effect for c in result.rounds[0]] if result.rounds else []
    width = 0.8 / max(len(rr), 1)
    seen: set[str] = set()
    top = 1.05
    low = 0.95
    for k, rnd in enumerate(rr):
        by = {c.effect: c for c in rnd if c.fit is not None}
        for m, e in enumerate(effects):
            c = by.get(e)
            x = m + k * width
            if c is None or not math.isfinite(c.gain):
                a.text(x, 1.0, "not\ntested", ha="center", va="bottom", fontsize=6, color="0.4")
                continue
            color, lab = _status(result, k, c)
            se = c.gain_se if math.isfinite(c.gain_se) else 0.0
            a.bar(
                x,
                c.gain - 1.0,
                bottom=1.0,
                width=width,
                color=color,
                edgecolor="k",
                lw=0.3,
                yerr=se,
                ecolor="k",
                capsize=2,
                label=None if lab in seen else lab,
            )
            seen.add(lab)
            a.text(x, max(c.gain, 1.0) + se, f"{c.gain:.3g}", ha="center", va="bottom", fontsize=6)
            top = max(top, c.gain + se)
            low = min(low, c.gain - se)
    a.axhline(1.0, color="k", lw=0.6)
    a.set_ylim(max(0.0, low - 0.05 * (top - low)), top + 0.12 * (top - low))
    a.set_xticks(np.arange(len(effects)) + 0.4 - width / 2)
    a.set_xticklabels(effects, rotation=45, fontsize=8)
    a.set_ylabel("held-out gain (RMS before / after)")
    rounds_txt = "" if len(rr) == 1 else f"; bars left to right: rounds 1-{len(rr)}"
    a.set_title(f"held-out gain per candidate (+- its standard error){rounds_txt}", fontsize=9)
    a.legend(fontsize=7, loc="upper left")


def _gains(plt: Any, result: AuditResult) -> Any:
    fig, ax = plt.subplots(1, 2, figsize=(13, 4.6))
    _gain_bars(ax[0], result)
    effects = [c.effect for c in result.rounds[0]] if result.rounds else []
    width = 0.8 / max(len(result.rounds), 1)
    for k, rnd in enumerate(result.rounds):
        b = {c.effect: c.bic_delta for c in rnd if c.fit is not None}
        for m, e in enumerate(effects):
            d = b.get(e, math.nan)
            x = m + k * width
            if not math.isfinite(d):
                continue
            if -d >= 1.0:
                ax[1].bar(
                    x,
                    -d,
                    width=width,
                    color=f"C{k}",
                    edgecolor="k",
                    lw=0.3,
                    label=f"round {k + 1}" if m == 0 else None,
                )
                ax[1].text(x, -d, f"{-d:.3g}", ha="center", va="bottom", fontsize=6)
            else:
                ax[1].text(x, 1.0, f"{-d:+.2g}", ha="center", va="bottom", fontsize=6, rotation=90)
    ax[1].axhline(
        result.options.bic_min,
        color="tab:green",
        lw=0.8,
        ls="--",
        label=f"threshold {result.options.bic_min:g}",
    )
    ax[1].set_yscale("log")
    ax[1].set_ylim(bottom=1.0)
    ax[1].set_xticks(np.arange(len(effects)) + 0.4 - width / 2)
    ax[1].set_xticklabels(effects, rotation=45, fontsize=8)
    ax[1].set_ylabel("BIC decrease of the training fit")
    ax[1].set_title("BIC decrease per candidate (numbers at the axis: no decrease)", fontsize=9)
    ax[1].legend(fontsize=7)
    fig.suptitle(f"piezod audit: what each candidate gains (cause {result.cause})", fontsize=10)
    fig.tight_layout()
    return fig


def _prediction(plt: Any, result: AuditResult) -> Any:
    """Measured position against the model's position (the target it predicts), fitted and held out."""
    data = result.data
    fig, ax = plt.subplots(1, 2, figsize=(12, 4.8))
    rows = data.fit_mask
    meas = data.position_um[rows]
    for fit, color, name in (
        (result.base_fit, "tab:red", "baseline"),
        (result.final_fit, "tab:blue", _label(result)),
    ):
        model = meas - fit.residual
        ax[0].plot(model, meas, ",", color=color, alpha=0.5, rasterized=True)
        ax[1].plot(model, fit.residual, ",", color=color, alpha=0.5, rasterized=True)
        ax[1].plot([], [], "s", color=color, label=f"{name}: rms {fit.rms_um:.3g} um")
    lo, hi = float(meas.min()), float(meas.max())
    ax[0].plot([lo, hi], [lo, hi], "k-", lw=0.6, label="measured = model")
    ax[0].set_xlabel("model position (um, offsets fitted)")
    ax[0].set_ylabel("measured position (um)")
    ax[0].set_title("measured position against the model's (fitted data)", fontsize=9)
    ax[0].legend(fontsize=7)
    if math.isfinite(result.noise_floor_um):
        for sgn in (-2.0, 2.0):
            ax[1].axhline(sgn * result.noise_floor_um, color="k", lw=0.6, ls="--")
    ax[1].set_xlabel("model position (um)")
    ax[1].set_ylabel("measured - model (um)")
    ax[1].set_title("deviation from the model (dashed: +-2 x noise floor)", fontsize=9)
    ax[1].legend(fontsize=7, markerscale=1)
    fig.tight_layout()
    return fig


def _structure(plt: Any, result: AuditResult) -> Any:
    """Only panels with something to show: binned residuals always, per-experiment ones with >= 3 points."""
    from piezod.audit.residuals import spectrum

    panels: list[tuple[str, Any]] = []
    pairs = (
        (result.base_structure, "tab:red", "baseline"),
        (result.final_structure, "tab:blue", _label(result)),
    )
    for key, xl in (
        ("voltage_v", "voltage (V)"),
        ("voltage_rate_v_per_s", "voltage rate (V/s)"),
        ("since_reversal_v", "voltage travelled since the last reversal (V)"),
    ):

        def binned(a: Any, key: str = key, xl: str = xl) -> None:
            for st, color, name in pairs:
                bn = st.bins[key]
                a.plot(bn["centre"], bn["mean_um"], "o-", color=color, ms=3, label=f"{name}: mean")
                a.plot(bn["centre"], bn["rms_um"], "s:", color=color, ms=3, label=f"{name}: rms")
            a.axhline(0.0, color="k", lw=0.4)
            a.set_xlabel(xl)
            a.set_ylabel("residual (um)")
            a.set_title(f"residual binned by {xl.split(' (')[0]}", fontsize=9)

        panels.append((key, binned))
    per = result.base_structure.per_experiment
    for key, xl, yk, yl, logx in (
        ("t_mid_s", "session time (s)", "gain_error_pct", "sensitivity error (%)", False),
        ("offset_v", "scan offset (V)", "gain_error_pct", "sensitivity error (%)", False),
        ("range_v", "scan range (V peak-to-peak)", "gain_error_pct", "sensitivity error (%)", False),
        ("frequency_hz", "line rate (Hz)", "gain_error_pct", "sensitivity error (%)", True),
        ("frequency_hz", "line rate (Hz)", "opening_error_um", "loop-opening error (um)", True),
    ):
        xv = np.array([p[key] for p in per], dtype=float)
        yv = np.array([p[yk] for p in per], dtype=float)
        ok = np.isfinite(xv) & np.isfinite(yv)
        if ok.sum() < 3 or np.unique(np.round(xv[ok], 9)).size < 3:
            continue

        def scatter(
            a: Any, key: str = key, xl: str = xl, yk: str = yk, yl: str = yl, logx: bool = logx
        ) -> None:
            for st, color, name in pairs:
                pe = st.per_experiment
                a.plot([p[key] for p in pe], [p[yk] for p in pe], "o", color=color, ms=4, label=name)
            a.axhline(0.0, color="k", lw=0.4)
            if logx:
                a.set_xscale("log")
            a.set_xlabel(xl)
            a.set_ylabel(yl)
            a.set_title(f"per experiment: {yl.split(' (')[0]} vs {xl.split(' (')[0]}", fontsize=9)

        panels.append((f"{key}:{yk}", scatter))

    def spectra(a: Any) -> None:
        for fit, color, name in (
            (result.base_fit, "tab:red", "baseline"),
            (result.final_fit, "tab:blue", _label(result)),
        ):
            fr, amp = spectrum(result.data, result.data.fit_mask, fit.residual)
            if fr.size:
                a.loglog(fr, amp, color=color, lw=0.8, label=name)
        a.set_xlabel("frequency (Hz)")
        a.set_ylabel("residual amplitude (um/sqrt(Hz))")
        a.set_title("residual spectrum", fontsize=9)

    panels.append(("spectrum", spectra))
    cols = 3
    rows = math.ceil(len(panels) / cols)
    fig, ax = plt.subplots(rows, cols, figsize=(13, 3.4 * rows + 0.6), squeeze=False)
    for j, (_, draw) in enumerate(panels):
        a = ax[j // cols, j % cols]
        draw(a)
        a.legend(fontsize=6)
    for j in range(len(panels), rows * cols):
        ax[j // cols, j % cols].set_visible(False)
    fig.suptitle(
        "structure of the residual: where the model is wrong (red baseline, blue final model)", fontsize=10
    )
    fig.tight_layout()
    return fig
