"""Image files: Gwyddion ``.gwy`` (with the ``gwyfile`` package) and PNG pictures.

A ``.gwy`` file of a recording holds every :class:`~piezod.image.ImagePair` as two data fields
(trace, retrace) in SI units (lateral m, height m or V), titled ``CHANNEL trace (GRID grid)``, each
with a metadata container (Gwyddion's *Metadata* browser) carrying what a lab needs to reproduce
the image: scan range and offset, slow range, rotation, line rate, pixels and lines, the model and
its parameters, the scanner config's SHA-256, the time of the scan, the recording and its metadata.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from piezod.image import F64, ImagePair, level


def image_metadata(pair: ImagePair, recording_meta: Mapping[str, str], source: str) -> dict[str, str]:
    """The metadata strings of one image (recording metadata first, then the image's own)."""
    g = pair.geometry
    meta = {f"recording.{k}": str(v) for k, v in recording_meta.items()}
    meta.update(
        {
            "source": source,
            "channel": pair.channel,
            "grid": pair.grid,
            "range_um": f"{g.range_um:.10g}",
            "offset_x_um": f"{g.offset_um:.10g}",
            "slow_range_um": f"{g.slow_range_um:.10g}",
            "offset_y_um": f"{g.offset_slow_um:.10g}",
            "rotation_deg": f"{g.rotation_deg:.10g}",
            "line_rate_hz": "" if g.line_rate_hz is None else f"{g.line_rate_hz:.10g}",
            "pixels": str(g.pixels),
            "lines": str(pair.trace.shape[0]),
            "unit": pair.unit,
        }
    )
    for key in ("model", "model_params", "config_sha256", "started_utc", "scanner", "correction"):
        if key in recording_meta:
            meta[key] = str(recording_meta[key])
    meta.update({str(k): str(v) for k, v in pair.notes.items()})
    return meta


def write_gwy(path: Path, pairs: Sequence[ImagePair], recording_meta: Mapping[str, str], source: str) -> Path:
    """Write the images to a Gwyddion file (channels ``0, 1, ...``: trace, retrace per pair)."""
    from gwyfile.objects import GwyContainer, GwyDataField

    obj = GwyContainer()
    k = 0
    for pair in pairs:
        g = pair.geometry
        meta = image_metadata(pair, recording_meta, source)
        for name, img in (("trace", pair.trace), ("retrace", pair.retrace)):
            data = np.ascontiguousarray(np.nan_to_num(img, nan=0.0) * pair.scale_to_si, dtype=np.float64)
            obj[f"/{k}/data"] = GwyDataField(
                data,
                xreal=g.range_um * 1e-6,
                yreal=max(g.slow_range_um, 1e-9) * 1e-6,
                xoff=g.x0_um * 1e-6,
                yoff=(g.offset_slow_um - 0.5 * g.slow_range_um) * 1e-6,
                si_unit_xy="m",
                si_unit_z=pair.unit,
            )
            obj[f"/{k}/data/title"] = f"{pair.channel} {name} ({pair.grid} grid)"
            obj.typecodes[f"/{k}/data/title"] = "s"
            entries = {**meta, "direction": name}
            # typecode 's' for every entry: gwyfile stores one-character strings as chars otherwise
            obj[f"/{k}/meta"] = GwyContainer(entries, typecodes=dict.fromkeys(entries, "s"))
            k += 1
    path.parent.mkdir(parents=True, exist_ok=True)
    obj.tofile(str(path))
    return path


def _display(pair: ImagePair) -> tuple[F64, F64, str]:
    if pair.unit == "m":
        return level(pair.trace) * 1e3, level(pair.retrace) * 1e3, "height (nm)"
    return level(pair.trace), level(pair.retrace), f"{pair.channel} ({pair.unit})"


def write_png(path: Path, pair: ImagePair, title: str) -> Path:
    """Trace and retrace side by side (plane-levelled, shared colour scale), labelled axes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tr, re, label = _display(pair)
    g = pair.geometry
    extent = (
        g.x0_um,
        g.x0_um + g.range_um,
        g.offset_slow_um - 0.5 * g.slow_range_um,
        g.offset_slow_um + 0.5 * g.slow_range_um,
    )
    both = np.concatenate((tr[np.isfinite(tr)], re[np.isfinite(re)]))
    lo, hi = np.percentile(both, [1, 99]) if both.size else (0.0, 1.0)
    fig, axes = plt.subplots(1, 2, figsize=(9.5, 4.2), constrained_layout=True)
    im = None
    for ax, img, name in zip(axes, (tr, re), ("trace", "retrace"), strict=True):
        im = ax.imshow(img, origin="lower", extent=extent, aspect="auto", cmap="afmhot", vmin=lo, vmax=hi)
        ax.set_xlabel("x, fast axis (um)")
        ax.set_ylabel("y, slow axis (um)")
        ax.set_title(f"{name} ({pair.grid} grid)")
    assert im is not None
    fig.colorbar(im, ax=axes, label=label, shrink=0.9)
    fig.suptitle(title)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


def model_metadata(model: str, params: Mapping[str, float]) -> dict[str, str]:
    """``model`` and ``model_params`` (JSON) metadata entries."""
    return {"model": model, "model_params": json.dumps(dict(params), sort_keys=True)}


def write_pair_png(
    left: ImagePair,
    right: ImagePair,
    path: Path,
    *,
    titles: tuple[str, str] = ("uncorrected", "corrected"),
    pitch_um: float | None = None,
    suptitle: str = "",
) -> Path:
    """Two trace images side by side (e.g. uncorrected vs corrected), with the reference's pitch grid.

    With ``pitch_um`` dotted lines mark where features of that pitch lie on a linear scan, anchored
    at the image centre: a linear image keeps its features on them.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9.0, 4.4), constrained_layout=True)
    for ax, pair, title in zip(axes, (left, right), titles, strict=True):
        g = pair.geometry
        img = level(pair.trace)
        if pair.unit == "m":
            img = img * 1e3
        lo, hi = np.nanpercentile(img, [1, 99])
        x0, x1 = g.x0_um, g.x0_um + g.range_um
        y0, y1 = g.offset_slow_um - 0.5 * g.slow_range_um, g.offset_slow_um + 0.5 * g.slow_range_um
        ax.imshow(
            img, origin="lower", extent=(x0, x1, y0, y1), aspect="equal", cmap="afmhot", vmin=lo, vmax=hi
        )
        if pitch_um:
            for k in np.arange(
                np.ceil((x0 - g.offset_um) / pitch_um), np.floor((x1 - g.offset_um) / pitch_um) + 1
            ):
                ax.axvline(g.offset_um + k * pitch_um, color="c", lw=0.7, ls=":")
        ax.set_xlabel("x, fast axis (um)")
        ax.set_ylabel("y, slow axis (um)")
        ax.set_title(title, fontsize=10)
    fig.suptitle(suptitle)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path


__all__ = ["image_metadata", "model_metadata", "write_gwy", "write_pair_png", "write_png"]
