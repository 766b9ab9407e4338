"""The columns of the offsets' consider sensitivity (:class:`ConsiderColumns`): what a
calibrated config's uncertainty, a stated unmodelled error and an encoder scale's sigma each
do to the link accelerometers' readings.

:class:`armfusion.fusion.tracking.observability.Observability` carries, per column, how far
that error has pulled the offsets' estimate (its ``consider`` matrix); this module says which
columns there are and what each one's error is in the readings now
(:meth:`ConsiderColumns.errors`).
"""

from __future__ import annotations

import numpy as np
from armfusion.fusion.tracking.frames import Frames
from armfusion.fusion.tracking.settings import IMU_ACC, G
from armfusion.models.motion import cross


class ConsiderColumns:
    """The columns of the consider sensitivity, for a tracker's link accelerometers
    ``link_names`` (of its accelerometer streams ``accel_streams``): each correction spread
    of a calibrated config (``spread``: per stream, the spreads as maps ``(M, c)``,
    ``StartupCorrection.spread`` inverted; ``correction`` the config's correction), and, per
    link accelerometer whose config states an unmodelled error (``unmodelled_g``, its
    ``calibration.accel_unmodelled_g``), one column per axis: an error of that size that
    stays (an uncalibrated ADXL345's offset and its board's tilt do not average away); and
    one per joint whose encoder scale has a sigma (``scale_sigma``). ``R_0I``: the IMU's
    mount (None without an IMU)."""

    def __init__(self, link_names: tuple[str, ...], accel_streams: tuple[str, ...], correction,
                 spread: dict, unmodelled_g: np.ndarray, scale_sigma: np.ndarray, R_0I: np.ndarray | None):
        self.accel_streams, self.correction, self._R_0I = accel_streams, correction, R_0I
        self._eye3 = np.eye(3)
        self._spread_cols: dict[str, np.ndarray] = {}
        self._spread_stack: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        self._floor_cols: dict[str, tuple[np.ndarray, float]] = {}
        m = 0
        for stream, maps in spread.items():
            if maps:
                self._spread_cols[stream] = np.arange(m, m + len(maps))
                self._spread_stack[stream] = (np.array([M for M, _ in maps]), np.array([c for _, c in maps]))
                m += len(maps)
        for stream, floor_g in zip(link_names, unmodelled_g.tolist(), strict=False):
            if floor_g > 0.0:
                self._floor_cols[stream] = (np.arange(m, m + 3), floor_g)
                m += 3
        # an encoder scale known to sigma_s moves the joint's true offset by sigma_s per radian
        # the encoder turns: one column per joint whose config gives that sigma
        self.scale_joints = np.flatnonzero(scale_sigma > 0.0)
        """The joints whose encoder scale has a sigma."""
        self.scale_sigma = scale_sigma[self.scale_joints]
        self.scale_cols = np.arange(m, m + len(self.scale_joints))
        """Their columns."""
        m += len(self.scale_joints)
        self.m = m
        """How many columns there are."""

    def errors(self, frame: Frames, sel: np.ndarray, v: np.ndarray, base: np.ndarray,
               accel_sigma_g: np.ndarray, accel_rate_hz: np.ndarray, window_s: float) -> np.ndarray:
        """Each correction spread's error in the used sensors' corrected readings, in the
        information rows' units (per sigma ``accel_sigma_g``, times sqrt(rate * window)):
        ``(k, 3, m)``, the columns in their order. ``sel``: the link accelerometers used;
        ``v (k, 3)``: their specific force (m/s², base axes); ``base``: the base's. A link
        accelerometer's spread errs on its own rows; the IMU's turns the base's reference
        (tilt and the chair's acceleration) for every link accelerometer at once."""
        k = len(sel)
        E = np.zeros((k, 3, self.m))
        R = frame.R_0S[sel]  # (k, 3, 3)
        f = np.einsum("kji,kj->ki", R, v) / G  # corrected readings, g (sensor axes)
        for i, s_idx in enumerate(sel.tolist()):
            stream = self.accel_streams[s_idx]
            floor = self._floor_cols.get(stream)
            if floor is not None:
                E[i, :, floor[0]] = floor[1] * self._eye3
            cols = self._spread_cols.get(stream)
            if cols is None:
                continue
            Lm, c = self.correction.maps[stream]
            raw = Lm @ f[i] + c
            M1, c1 = self._spread_stack[stream]  # (m_s, 3, 3), (m_s, 3)
            E[i, :, cols] = (M1 @ raw - np.einsum("mab,mb->ma", M1, c1) - f[i])
        cols = self._spread_cols.get(IMU_ACC) if self._R_0I is not None else None
        if cols is not None:
            Lm, c = self.correction.maps[IMU_ACC]
            raw = Lm @ (self._R_0I.T @ base / G) + c
            y0 = np.linalg.solve(Lm, raw - c)
            M1, c1 = self._spread_stack[IMU_ACC]
            d = M1 @ raw - np.einsum("mab,mb->ma", M1, c1) - y0  # (m_s, 3)
            r = cross(y0 / np.linalg.norm(y0), d) @ self._R_0I.T  # the reference turned by
            # each link sensor's reading error: R^T (r x v) / g
            rv = cross(r[:, None, :], v[None, :, :])  # (m_s, k, 3)
            E[:, :, cols] = np.einsum("kji,mkj->kim", R, rv) / G
        scale = np.sqrt(accel_rate_hz[sel] * window_s)
        return E / accel_sigma_g[sel][:, :, None] * scale[:, None, None]
