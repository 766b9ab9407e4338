"""The unit vocabulary sensor descriptions and the importer share (sensors/units.py)."""

import numpy as np
import pytest
from armfusion.sensors.units import UnitError, canonical_unit_name, convert, factor, quantity_of, units_of


def test_physical_units_convert_through_their_quantity():
    assert convert([1.0, -0.5], "g", "m/s^2") == pytest.approx([9.80665, -4.903325])
    assert convert(180.0, "deg/s", "rad/s") == pytest.approx(np.pi)
    assert convert(0.5, "gauss", "uT") == pytest.approx(50.0)
    assert factor("ms", "s") == pytest.approx(1e-3)
    # aliases a datasheet or a logger's header uses
    assert canonical_unit_name("m/s²") == "m/s^2" and canonical_unit_name("µT") == "uT"
    assert quantity_of("dps") == "angular_rate" and quantity_of("counts") is None
    assert units_of("acceleration")[0] == "g"


def test_wrong_or_unknown_units_are_refused_by_name():
    with pytest.raises(UnitError, match=r"cannot convert deg/s \(angular_rate\) to g \(acceleration\)"):
        factor("deg/s", "g")
    with pytest.raises(UnitError, match="through the device's scale"):
        factor("counts", "g")
    with pytest.raises(UnitError, match="unknown unit 'furlongs'"):
        canonical_unit_name("furlongs")
    with pytest.raises(UnitError, match=r"unknown unit 'xxxxxxxxxxxxxxxx…'"):
        canonical_unit_name("x" * 10_000)
