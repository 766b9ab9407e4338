"""A stream of an arm from its source columns: what the config says the stream is (its kind,
channels and the unit its values are recorded in, ``StreamModel.value_unit``), and the
source's values brought into that unit.

- into a physical unit (a sensor described as delivering g, deg/s…): the source's unit must
  be of the same quantity, converted by :func:`armfusion.sensors.units.convert`;
- into counts (a sensor described by its register counts, as the ADXL345 today): a physical
  source becomes counts through the description's nominal gain and zero
  (``StreamModel.to_counts``), unrounded (a value between two counts keeps what it says);
- the encoders: an angle becomes whole counts with the config's ``counts_per_rev``, refused
  when a value would move by more than the map's ``max_rounding_counts``; the import says
  how much it rounded;
- the truth streams ``true_q`` (one angle per joint) and ``true_base`` (roll, pitch, yaw) in rad.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from armfusion.fusion.importing.column_map import ColumnMap, StreamSource
from armfusion.models.arm import ArmModel
from armfusion.models.sensor_models import ENCODER_STREAM, StreamModel, stream_models
from armfusion.sensors.samples import TRUTH_BASE_COLUMNS, StreamKind, truth_joint_columns
from armfusion.sensors.units import COUNTS, UnitError, convert, factor, quantity_of


class ImportMapError(ValueError):
    """The column map does not fit the arm's config or the file; the message names the
    stream, the column, the file and the unit."""


@dataclass(frozen=True)
class Target:
    """A stream an arm's recording may hold: its kind, channels, the quantity its values
    measure, the unit they are recorded in, and its count model (None for truth)."""

    stream: str
    kind: StreamKind
    channels: tuple[str, ...]
    quantity: str
    value_unit: str
    model: StreamModel | None
    needed: bool

    @property
    def physical_unit(self) -> str:
        """The unit of the quantity the model converts from (the truth: rad)."""
        return self.model.unit if self.model is not None else self.value_unit


def targets(arm: ArmModel) -> dict[str, Target]:
    """Every stream ``arm``'s recording may hold, by name. Needed: the encoders and every
    stream of a sensor on a link (the base IMU's streams are optional)."""
    base = arm.imu.name if arm.imu is not None else None
    out: dict[str, Target] = {}
    for name, m in stream_models(arm).items():
        needed = name == ENCODER_STREAM or (bool(m.sensor) and m.sensor != base)
        out[name] = Target(name, m.kind, m.channels, quantity_of(m.unit) or "", m.value_unit, m, needed)
    out["true_q"] = Target("true_q", "truth_joints", truth_joint_columns(arm.n_joints), "angle", "rad",
                           None, False)
    out["true_base"] = Target("true_base", "truth_base", TRUTH_BASE_COLUMNS, "angle", "rad", None, False)
    return out


def check_map_against(cmap: ColumnMap, arm: ArmModel, config: str) -> dict[str, Target]:
    """The targets of the map's streams, or :class:`ImportMapError` listing every stream the
    config lacks, a wrong number of columns, a unit of another quantity, and every needed
    stream that the map neither gives nor declares absent."""
    all_targets = targets(arm)
    problems = []
    for name, src in cmap.streams.items():
        t = all_targets.get(name)
        if t is None:
            problems.append(f"streams.{name}: the config {config} has no stream {name!r}; its streams: "
                            + ", ".join(all_targets))
            continue
        if len(src.columns) != len(t.channels):
            problems.append(f"streams.{name}: {len(src.columns)} column(s) for a stream of "
                            f"{len(t.channels)} ({', '.join(t.channels)})")
        why = unit_problem(src.unit, t)
        if why:
            problems.append(f"streams.{name}: columns {', '.join(src.columns)}: {why}")
    for name in cmap.absent:
        if name not in all_targets:
            problems.append(f"absent.{name}: the config {config} has no stream {name!r}")
    missing = [t.stream for t in all_targets.values()
               if t.needed and t.stream not in cmap.streams and t.stream not in cmap.absent]
    if missing:
        problems.append(f"the config {config} needs stream(s) {', '.join(missing)}, which the map does "
                        "not give: map their columns under streams, or say under absent why the file "
                        "lacks them")
    if problems:
        raise ImportMapError(f"column map {cmap.source} does not fit the config {config}:\n"
                             + "\n".join(f"  - {p}" for p in problems))
    return {name: all_targets[name] for name in cmap.streams}


def unit_problem(unit: str, t: Target) -> str | None:
    """Why values in ``unit`` cannot become stream ``t``'s values, or None."""
    if unit == COUNTS:
        if t.value_unit == COUNTS:
            return None
        return (f"unit counts cannot become {t.value_unit}: the config describes {t.stream} as "
                f"delivering {t.value_unit}, and counts need a device's scale")
    q = quantity_of(unit)
    if q != t.quantity:
        return (f"unit {unit} ({q}) cannot become the stream's {t.value_unit} "
                f"({t.quantity}{', through the sensor model' if t.value_unit == COUNTS else ''})")
    return None


@dataclass(frozen=True)
class Converted:
    """A stream's values in its recorded unit, and how they were made: the factor (or the
    count model's gain) applied, and for the encoders the rounding to whole counts."""

    values: np.ndarray
    how: str
    rounding_max_counts: float | None = None
    rounding_rms_counts: float | None = None


def convert_values(values: np.ndarray, src: StreamSource, t: Target, source_file: str) -> Converted:
    """``values (N, k)`` in ``src.unit`` into ``t``'s recorded unit (see the module's docstring).
    NaN stays NaN (the caller has already taken the gaps out)."""
    if src.unit == t.value_unit:
        return Converted(values, f"kept in {t.value_unit}")
    if t.value_unit != COUNTS:
        try:
            f = factor(src.unit, t.value_unit)
        except UnitError as e:  # checked before; kept for a direct caller
            raise ImportMapError(f"{source_file}: {', '.join(src.columns)}: {e}") from None
        return Converted(convert(values, src.unit, t.value_unit),
                         f"{src.unit} -> {t.value_unit} (x {f:.12g})")
    physical = convert(values, src.unit, t.physical_unit)
    counts = t.model.to_counts(physical)
    how = (f"{src.unit} -> {t.physical_unit} -> counts with the config's gain "
           f"{', '.join(f'{g:.8g}' for g in np.atleast_1d(t.model.gain)[:3])} counts/{t.physical_unit}")
    if t.kind != "encoder":
        return Converted(counts, how + " (unrounded: the values are not register counts)")
    whole = np.rint(counts)
    off = np.abs(counts - whole)
    worst = float(off.max()) if off.size else 0.0
    if worst > src.max_rounding_counts:
        i, j = np.unravel_index(int(np.argmax(off)), off.shape)
        per_count_deg = 360.0 / (float(t.model.gain[j]) * 2 * np.pi)
        raise ImportMapError(
            f"{source_file}: column {src.columns[j]} ({src.unit}) into {t.stream} "
            f"({t.channels[j]}): the config's encoder ({per_count_deg:.6g} deg a count) would round "
            f"the angles by up to {worst:.3f} counts ({worst * per_count_deg:.4g} deg, data row {i + 1}), "
            f"more than the map allows ({src.max_rounding_counts} counts): use a config whose "
            f"counts_per_rev is the encoder's, or allow it with max_rounding_counts in the map's "
            f"{t.stream} entry")
    rms = float(np.sqrt(np.mean(off**2))) if off.size else 0.0
    if whole.size and not float(np.abs(whole).max()) < 2.0**63:  # no int64 holds it: kept as it is,
        return Converted(whole, how + ", rounded to whole counts", worst, rms)  # for the admission to name
    return Converted(whole.astype(np.int64), how + ", rounded to whole counts", worst, rms)
