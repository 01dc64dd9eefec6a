"""The simulated microscope: a tip on a sample surface, held by a z feedback that drives the z piezo.

Per block of samples (vectorised, a fixed number of passes, never per sample in Python):

1. The tip sits at the *true* lateral position of the scanner (the stage's x and y, before any
   sensor): it touches the surface height ``h(x, y)`` of the :class:`~hil_sim.sample.Sample`.
2. An idealised z feedback: the z piezo's extension follows ``h`` through a first-order loop of
   bandwidth ``feedback_bandwidth_hz`` (the tracking lag of a real PI loop) plus white
   ``height_noise_nm_rms`` (tip-sample and loop noise); that is the *true* z extension.
3. The z voltage that produces this extension on the stage's z axis - with the z axis's own
   hysteresis and creep (:class:`hil_sim.stage.Stage` of the z axis) - found by
   ``feedback_passes`` damped secant passes over the block from the z stage's snapshot, the last
   pass leaving the stage in its new state. What the passes do not remove is the loop's
   residual error (reported by :attr:`Microscope.last_error_nm_rms`).

The board records the z voltage as the height signal (SPM controllers record height as the z-piezo
voltage: thesis chapter 5), through the HV amplifier's monitor output (``V / monitor_ratio``) on
the z channel's ADC. The true extension is kept for tests (the truth a capacitive z sensor sees).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.signal import lfilter

from hil_sim.sample import Sample, get_sample
from hil_sim.stage import Stage, StageConfig

F64 = NDArray[np.float64]

MONITOR_RATIO = 100.0
"""The HV amplifier's monitor output is the z voltage divided by this (a 1:100 monitor)."""


@dataclass(frozen=True, slots=True)
class MicroscopeConfig:
    """The simulated microscope.

    Attributes
    ----------
    sample
        Name of the sample (:data:`hil_sim.sample.SAMPLES`).
    position_sensor
        False: the board has no position sensor (its x / y ADC channels read 0).
    feedback_bandwidth_hz
        -3 dB bandwidth of the z loop (Hz).
    height_noise_nm_rms
        Noise of the tip height (nm rms).
    feedback_passes
        Most secant passes per block that find the z voltage; the passes stop once the block's
        residual (target - true extension) is below ``feedback_tolerance_nm`` rms (1 nm) (a block on a
        plateau needs two, one with an edge of a z piezo whose slope changes at every reversal -
        Prandtl-Ishlinskii plays - up to eight).
    feedback_tolerance_nm
        RMS residual per block at which the passes stop (nm).
    monitor_ratio
        The z channel's ADC reads ``V_z / monitor_ratio``.
    seed
        Seed of the height noise.
    """

    sample: str = "line-3um"
    position_sensor: bool = True
    feedback_bandwidth_hz: float = 2000.0
    height_noise_nm_rms: float = 0.2
    feedback_passes: int = 8
    feedback_tolerance_nm: float = 1.0
    monitor_ratio: float = MONITOR_RATIO
    seed: int = 0

    def __post_init__(self) -> None:
        get_sample(self.sample)
        if not (math.isfinite(self.feedback_bandwidth_hz) and self.feedback_bandwidth_hz > 0):
            bw = self.feedback_bandwidth_hz
            raise ValueError(f"microscope: feedback_bandwidth_hz must be > 0, got {bw!r}")
        if not self.height_noise_nm_rms >= 0:
            raise ValueError(f"microscope: height_noise_nm_rms must be >= 0, got {self.height_noise_nm_rms}")
        if not 1 <= self.feedback_passes <= 20:
            raise ValueError(f"microscope: feedback_passes must be in [1, 20], got {self.feedback_passes}")
        if not self.monitor_ratio > 0:
            raise ValueError(f"microscope: monitor_ratio must be > 0, got {self.monitor_ratio}")


class Microscope:
    """Tip, surface and z feedback on the z axis of a simulated stage.

    Parameters
    ----------
    config
        The microscope.
    stage_config
        The true stage; its ``z`` axis is the z piezo.
    """

    def __init__(self, config: MicroscopeConfig, stage_config: StageConfig) -> None:
        self._cfg = config
        self._sample: Sample = get_sample(config.sample)
        self._z = Stage(stage_config, axes=("z",))
        ax = stage_config.axes["z"]
        self._b = float(ax.b_um_per_v)
        self._u = float(ax.u_um_per_v) if ax.u_um_per_v is not None else 0.6 * self._b
        self._rng = np.random.default_rng(config.seed)
        self._lp_state = 0.0
        self._lp_init = False
        self._v_last = 0.0
        self._e_last = 0.0
        self._slope = 0.5 * (self._b + self._u)
        self._err_rms_nm = 0.0

    @property
    def config(self) -> MicroscopeConfig:
        """The microscope's configuration."""
        return self._cfg

    @property
    def sample(self) -> Sample:
        """The sample under the tip."""
        return self._sample

    @property
    def last_error_nm_rms(self) -> float:
        """RMS of the loop's residual (target extension - true extension) over the last block (nm)."""
        return self._err_rms_nm

    def step(self, x_um: F64, y_um: F64, dt_s: float) -> tuple[F64, F64]:
        """Follow the surface over one block.

        Parameters
        ----------
        x_um, y_um
            True lateral tip positions (um), shape ``(n,)``.
        dt_s
            Sample interval (s).

        Returns
        -------
        z_voltage_v, z_um
            The z-piezo voltage (V, what the controller records) and the true z extension (um).
        """
        h = self._sample.height(x_um, y_um)
        n = h.size
        if n == 0:
            return np.zeros(0), np.zeros(0)
        a = math.exp(-2.0 * math.pi * self._cfg.feedback_bandwidth_hz * dt_s)
        if not self._lp_init:
            self._lp_state = float(h[0])
            self._lp_init = True
        target, _ = lfilter([1.0 - a], [1.0, -a], h, zi=[a * self._lp_state])
        self._lp_state = float(target[-1])
        if self._cfg.height_noise_nm_rms > 0:
            target = target + self._rng.normal(0.0, self._cfg.height_noise_nm_rms * 1e-3, n)
        snap = self._z.snapshot()
        # first guess from the slope dz/dV seen in the previous block; later passes: per-sample secants
        v = self._v_last + (target - self._e_last) / self._slope
        v_prev: F64 | None = None
        e_prev: F64 | None = None
        e = np.zeros(n)
        for k in range(self._cfg.feedback_passes):
            if k:
                self._z.restore(snap)
            e = self._z.step(v, dt_s)
            if k == self._cfg.feedback_passes - 1:
                break
            if k and float(np.sqrt(np.mean((target - e) ** 2))) * 1e3 < self._cfg.feedback_tolerance_nm:
                break
            slope = np.full(n, self._slope)
            if v_prev is not None and e_prev is not None:
                dv = v - v_prev
                ok = np.abs(dv) > 1e-9
                slope[ok] = np.clip((e - e_prev)[ok] / dv[ok], 0.2 * self._b, 1.5 * self._b)
            v_prev, e_prev = v, e
            v = v + (target - e) / slope
        if v_prev is not None and e_prev is not None:
            dv = v - v_prev
            dd = float(dv @ dv)
            if dd > 1e-12:
                self._slope = float(np.clip(float(dv @ (e - e_prev)) / dd, 0.2 * self._b, 1.5 * self._b))
        self._v_last = float(v[-1])
        self._e_last = float(e[-1])
        self._err_rms_nm = float(np.sqrt(np.mean((target - e) ** 2)) * 1e3)
        return v, e


__all__ = ["MONITOR_RATIO", "Microscope", "MicroscopeConfig"]
