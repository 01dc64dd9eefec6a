"""Sample surfaces of the simulated microscope: length standards with realistic imperfections.

A :class:`Sample` is a height map ``h(x, y)`` (um) over stage coordinates (um), evaluated
vectorised for any points (pure numpy, deterministic for a seed). The named samples
(:data:`SAMPLES`, ``piezod sim --sample NAME``):

``line-3um``
    The 1D line pattern of 3.0 um period (the thesis's 1D3000): lines 1.5 um wide and 100 nm
    high running along y, so the profile along the fast axis x is a square wave. Imperfections:
    edge roughness (each edge wanders along y, ``roughness_nm_rms``), one missing line, a sample
    tilt, and a defect (a particle, 0.4 um radius, 150 nm high) to recognise.
``grating-200nm``
    A 2D grating of 200 nm pitch (the thesis's 2D200): square posts of half the pitch, 20 nm high;
    edge roughness, tilt and a particle.
``grating-10um``
    A 2D grating of 10 um pitch: square posts of 5 um, 100 nm high; a missing post, tilt, a particle.
``steps-100nm``
    Terraces along x: 100 nm steps up and down, each plateau 4 um long (thesis chapter 5, the z
    overshoots of figs 5.3-5.4); no roughness, no tilt.
``flat``
    A flat surface (height 0).

The pitch of a pattern is exact (it is a certified standard); the line width is not used by the
analysis. Edges are smooth over ``edge_width_nm`` (logistic profile), far below a pixel of the
usual images.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]

_ROUGH_TABLE = 4096
"""Lines (or posts per row) with their own roughness phases; indices wrap beyond."""
_ROUGH_WAVELENGTHS_UM = (0.35, 0.8, 1.9, 4.3)


@dataclass(frozen=True, slots=True)
class Defect:
    """A particle on the surface: a smooth bump.

    Attributes
    ----------
    x_um, y_um
        Centre (um).
    radius_um
        Radius (um).
    height_um
        Height (um).
    """

    x_um: float
    y_um: float
    radius_um: float
    height_um: float


@dataclass(frozen=True, slots=True)
class Sample:
    """A sample surface.

    Attributes
    ----------
    name
        The sample's name.
    kind
        ``"lines"`` (1D pattern along x), ``"grating"`` (2D posts), ``"steps"`` (terraces along x)
        or ``"flat"``.
    pitch_um
        Period of the pattern (um); for steps, the length of one up + down plateau pair.
    duty
        Fraction of a period covered by the line / post / upper terrace.
    height_um
        Height of the lines / posts / steps (um).
    edge_width_nm
        Width of the logistic edge profile (nm).
    roughness_nm_rms
        RMS of each edge's wander (nm), smooth along the edge (wavelengths 0.35-4.3 um).
    missing
        Indices of missing lines (1D: line ``k`` is centred on ``x = k * pitch``; 2D: ``(kx, ky)`` flattened
        as ``kx + 1000 * ky``).
    tilt_x, tilt_y
        Sample tilt (um of height per um).
    defects
        Particles on the surface.
    seed
        Seed of the edge roughness.
    """

    name: str
    kind: str
    pitch_um: float
    duty: float = 0.5
    height_um: float = 0.1
    edge_width_nm: float = 15.0
    roughness_nm_rms: float = 0.0
    missing: tuple[int, ...] = ()
    tilt_x: float = 0.0
    tilt_y: float = 0.0
    defects: tuple[Defect, ...] = ()
    seed: int = 0

    def _phases(self) -> tuple[F64, F64]:
        rng = np.random.default_rng(self.seed)
        phases = rng.uniform(0.0, 2.0 * np.pi, size=(2, _ROUGH_TABLE, len(_ROUGH_WAVELENGTHS_UM)))
        return phases[0], phases[1]

    def _wander(self, k: NDArray[np.int64], along: F64, phases: F64) -> F64:
        """Edge displacement (um) of edge family ``k`` at coordinate ``along`` (um)."""
        if self.roughness_nm_rms <= 0.0:
            return np.zeros_like(along)
        m = len(_ROUGH_WAVELENGTHS_UM)
        amp = self.roughness_nm_rms * 1e-3 * np.sqrt(2.0 / m)
        ph = phases[np.mod(k, _ROUGH_TABLE)]
        out = np.zeros_like(along)
        for j, lam in enumerate(_ROUGH_WAVELENGTHS_UM):
            out += amp * np.sin(2.0 * np.pi * along / lam + ph[..., j])
        return out

    def _bar(self, u: F64, k: NDArray[np.int64]) -> F64:
        """Square wave centred on ``k p``: 1 on ``|u - k p| < duty p / 2``, logistic edges (um)."""
        e = max(self.edge_width_nm * 1e-3, 1e-6)
        s = u - k * self.pitch_um
        hw = 0.5 * self.duty * self.pitch_um
        left = 1.0 / (1.0 + np.exp(-np.clip((s + hw) / e, -60.0, 60.0)))
        right = 1.0 / (1.0 + np.exp(-np.clip((s - hw) / e, -60.0, 60.0)))
        out: F64 = left - right
        return out

    def height(self, x_um: ArrayLike, y_um: ArrayLike) -> F64:
        """Height (um) at the points ``(x_um, y_um)`` (broadcast)."""
        x, y = np.broadcast_arrays(np.asarray(x_um, dtype=np.float64), np.asarray(y_um, dtype=np.float64))
        h = np.zeros(x.shape)
        p = self.pitch_um
        if self.kind in ("lines", "steps"):
            px, _ = self._phases()
            k0 = np.rint(x / p).astype(np.int64)
            u = x - self._wander(k0, y, px)
            k = np.rint(u / p).astype(np.int64)
            bar = self._bar(u, k)
            if self.missing:
                bar = np.where(np.isin(k, self.missing), 0.0, bar)
            h = self.height_um * bar
        elif self.kind == "grating":
            px, py = self._phases()
            kx0 = np.rint(x / p).astype(np.int64)
            ky0 = np.rint(y / p).astype(np.int64)
            u = x - self._wander(kx0 + 7 * ky0, y, px)
            v = y - self._wander(ky0 + 13 * kx0, x, py)
            kx = np.rint(u / p).astype(np.int64)
            ky = np.rint(v / p).astype(np.int64)
            post = self._bar(u, kx) * self._bar(v, ky)
            if self.missing:
                post = np.where(np.isin(kx + 1000 * ky, self.missing), 0.0, post)
            h = self.height_um * post
        elif self.kind != "flat":
            raise ValueError(f"sample {self.name!r}: unknown kind {self.kind!r}")
        h = h + self.tilt_x * x + self.tilt_y * y
        for d in self.defects:
            r2 = ((x - d.x_um) ** 2 + (y - d.y_um) ** 2) / (d.radius_um**2)
            h = h + d.height_um * np.exp(-(np.minimum(r2, 50.0) ** 2))
        return h


SAMPLES: dict[str, Sample] = {
    "line-3um": Sample(
        name="line-3um",
        kind="lines",
        pitch_um=3.0,
        duty=0.5,
        height_um=0.1,
        edge_width_nm=15.0,
        roughness_nm_rms=3.0,
        missing=(2,),
        tilt_x=2e-3,
        tilt_y=-1e-3,
        defects=(Defect(x_um=-7.3, y_um=4.1, radius_um=0.4, height_um=0.15),),
        seed=3000,
    ),
    "grating-200nm": Sample(
        name="grating-200nm",
        kind="grating",
        pitch_um=0.2,
        duty=0.5,
        height_um=0.02,
        edge_width_nm=4.0,
        roughness_nm_rms=1.0,
        missing=(3 + 1000 * 2,),
        tilt_x=1e-3,
        tilt_y=5e-4,
        defects=(Defect(x_um=0.9, y_um=-0.6, radius_um=0.08, height_um=0.05),),
        seed=200,
    ),
    "grating-10um": Sample(
        name="grating-10um",
        kind="grating",
        pitch_um=10.0,
        duty=0.5,
        height_um=0.1,
        edge_width_nm=30.0,
        roughness_nm_rms=5.0,
        missing=(1 + 1000 * 0,),
        tilt_x=2e-3,
        tilt_y=1e-3,
        defects=(Defect(x_um=-6.0, y_um=7.0, radius_um=0.8, height_um=0.2),),
        seed=10,
    ),
    "steps-100nm": Sample(
        name="steps-100nm", kind="steps", pitch_um=8.0, duty=0.5, height_um=0.1, edge_width_nm=20.0
    ),
    "flat": Sample(name="flat", kind="flat", pitch_um=1.0, height_um=0.0),
}
"""The named samples (``piezod sim --sample NAME``)."""


def get_sample(name: str) -> Sample:
    """The named sample.

    Raises
    ------
    ValueError
        Unknown name (the message lists the known ones).
    """
    try:
        return SAMPLES[name]
    except KeyError:
        raise ValueError(f"unknown sample {name!r} (known: {', '.join(SAMPLES)})") from None


__all__ = ["SAMPLES", "Defect", "Sample", "get_sample"]
