"""What a started tracker holds and reports, read only (:class:`TrackerReadout`, which
:class:`armfusion.fusion.tracking.filter.Tracker` extends with its lifecycle and its one filter path):
the filter (its mean and covariance), the time of the last fused instant, the encoders'
angles, the joints' flags and the gyro's last reading, and the results by value: the
estimate, the combinations gravity reads, the counters, NIS, warnings and innovations
(:class:`armfusion.fusion.tracking.report.Reports`, :class:`armfusion.fusion.tracking.combos.JointTiltCombinations`)."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from armfusion.fusion.startup.combinations import Combination
from armfusion.fusion.tracking.combos import JointTiltCombinations
from armfusion.fusion.tracking.compass import Compass
from armfusion.fusion.tracking.estimate import Estimate
from armfusion.fusion.tracking.health import SensorHealth
from armfusion.fusion.tracking.initial import Ambiguity
from armfusion.fusion.tracking.innovations import InnovationLog
from armfusion.fusion.tracking.report import Reports
from armfusion.fusion.tracking.settings import NotInitialisedError, TrackerSettings
from armfusion.fusion.tracking.setup import TrackerSetup
from armfusion.fusion.tracking.ukf import BatchedUKF
from armfusion.models.arm import ArmModel


class TrackerReadout(TrackerSetup):
    """A tracker's held values and its results by value (see the module's docstring); a
    :class:`armfusion.fusion.tracking.filter.Tracker`'s lifecycle writes them."""

    def __init__(self, arm: ArmModel, settings: TrackerSettings | None = None,
                 rates_hz: Mapping[str, float] | float = 100.0, correction=None):
        super().__init__(arm, settings, rates_hz, correction)
        self._ukf: BatchedUKF | None = None
        self._t: float | None = None
        self._q_enc = np.zeros(self.arm.n_joints)
        self._flags = np.zeros(self.arm.n_joints, dtype=np.int8)
        self._omega: np.ndarray | None = None
        self._combos: JointTiltCombinations | None = None
        self._reports: Reports | None = None
        self.health: SensorHealth | None = None
        self.compass: Compass | None = None
        self.ambiguity_: Ambiguity | None = None

    def _check(self) -> None:
        if self._t is None:
            raise NotInitialisedError("the tracker is not initialised: call initialise(startup, t) "
                                      "with a startup calibration first")

    def _check_filter(self) -> None:
        self._check()
        if self._ukf is None:
            raise NotInitialisedError("no encoder sample yet: the first one fixes the offsets")

    @property
    def initialised(self) -> bool:
        return self._t is not None

    @property
    def t_s(self) -> float | None:
        return self._t

    @property
    def filter_started(self) -> bool:
        """Whether the filter runs (the first encoder sample has fixed the offsets)."""
        return self._ukf is not None

    @property
    def mean(self) -> np.ndarray:
        """The filter's mean itself, not a copy (:attr:`x` is one): for reading at once
        (:attr:`armfusion.fusion.tracking.ukf.BatchedUKF.mean`)."""
        return self._ukf.mean

    @property
    def covariance(self) -> np.ndarray:
        """The filter's covariance itself, not a copy (:attr:`P` is one); as :attr:`mean`."""
        return self._ukf.covariance

    @property
    def q_enc(self) -> np.ndarray:
        """The encoders' angles at the last fused instant (rad) itself, not a copy
        (:meth:`q_enc_now` is one): replaced at every instant, never written into."""
        return self._q_enc

    @property
    def joint_flag_codes(self) -> np.ndarray:
        """The joints' flags (codes of :data:`armfusion.fusion.tracking.settings.JOINT_FLAGS`) as last
        worked out: replaced when they are, never written into (a reader may keep it and
        compare by identity)."""
        return self._flags

    @property
    def last_gyro_B(self) -> np.ndarray | None:
        """The gyro's last reading, base axes (rad/s); None before any."""
        return self._omega

    @last_gyro_B.setter
    def last_gyro_B(self, w: np.ndarray | None) -> None:
        """Prime it (a start from a recording's still window, before the first step)."""
        self._omega = None if w is None else np.asarray(w, dtype=float)

    @property
    def x(self) -> np.ndarray:
        """The filter's state (read-only copy; names in :attr:`state_names`)."""
        self._check_filter()
        return self._ukf.x

    @property
    def P(self) -> np.ndarray:
        self._check_filter()
        return self._ukf.P

    # -- results (by value) ------------------------------------------------------------------
    def ambiguity(self) -> dict[str, tuple[float, ...]]:
        """Per joint the startup left ``ambiguous``: its candidate angles now (the startup's,
        moved by what the encoders counted since), rad. Empty once every branch is known."""
        return self.ambiguity_.at(self.arm.joint_names, self._q_enc)

    def q_enc_now(self) -> np.ndarray:
        """The encoders' angles (counts / counts per rad) at the last fused instant."""
        return self._q_enc.copy()

    def combination_vectors(self) -> tuple[tuple[Combination, ...], np.ndarray, np.ndarray]:
        """What gravity reads where it cannot read single joints, now
        (:meth:`armfusion.fusion.tracking.combos.JointTiltCombinations.vectors`)."""
        self._check_filter()
        return self._combos.vectors(self._ukf, self._q_enc, self._flags)

    def combination_values(self, C: np.ndarray, ix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The combinations of coefficients ``C`` (from :meth:`combination_vectors`) now: their
        values and sigmas (rad)."""
        return self._combos.values(self._ukf, self._q_enc, C, ix)

    def combinations_now(self) -> tuple[Combination, ...]:
        """:meth:`combination_vectors`' combinations at the last fused instant
        (:meth:`armfusion.fusion.tracking.combos.JointTiltCombinations.now`)."""
        return self._combos.now(self._ukf, self._q_enc, self._flags, self._t)

    @property
    def estimate(self) -> Estimate:
        """The estimate at the last fused instant (:meth:`armfusion.fusion.tracking.report.Reports.estimate`)."""
        self._check_filter()
        return self._reports.estimate(self._t, self._ukf, self._q_enc, self._flags)

    def gyro_scale(self) -> dict | None:
        """The gyro's scale error as the filter holds it
        (:meth:`armfusion.fusion.tracking.report.Reports.gyro_scale`)."""
        self._check()
        return self._reports.gyro_scale(self._ukf)

    def heading_status_code(self) -> int:
        """The heading's status (:meth:`armfusion.fusion.tracking.report.Reports.heading_status_code`)."""
        return self._reports.heading_status_code()

    def counters(self) -> dict[str, dict[str, int]]:
        """Per sensor: samples, used, rejected, nan, saturated, implausible, stuck,
        out_of_order, reacquisitions."""
        self._check()
        return self.health.counters()

    def sensor_warnings(self) -> list[str]:
        """The accelerometers rejected too often (:meth:`armfusion.fusion.tracking.report.Reports.sensor_warnings`)."""
        self._check()
        return self._reports.sensor_warnings()

    def innovations(self, sensor: str) -> InnovationLog:
        """The innovations kept for ``sensor`` (:meth:`armfusion.fusion.tracking.report.Reports.innovations`)."""
        self._check()
        return self._reports.innovations(sensor)

    def nis_stats(self) -> dict[str, tuple[float, int, int]]:
        """Per sensor: (mean NIS, count, degrees of freedom) over its healthy samples."""
        self._check()
        return self._reports.nis_stats()
