"""Which sensor a compass slot is (issue 26, repeatability across flights): a theta is compared between two
flights only for the same physical sensor, named by the log's own parameters, not by slot index."""

from __future__ import annotations

from magcomp.diagnosis.identity import group_by_sensor, sensor_identity

#: yladzislay's Pixhawk 1 (the development logs): an external HMC5883 on I2C and the board's LSM303D on SPI;
#: with the GPS module unplugged the LSM303D moves up to slot 0
WITH_GPS = {
    "COMPASS_DEV_ID": 466441.0,
    "COMPASS_DEV_ID2": 131594.0,
    "COMPASS_DEV_ID3": 0.0,
    "COMPASS_EXTERNAL": 1.0,
    "COMPASS_EXTERN2": 0.0,
}
WITHOUT_GPS = {"COMPASS_DEV_ID": 131594.0, "COMPASS_DEV_ID2": 0.0, "COMPASS_EXTERNAL": 0.0}


def test_ardupilot_slots_name_their_sensor() -> None:
    a0, a1 = sensor_identity(WITH_GPS, 0), sensor_identity(WITH_GPS, 1)
    b0 = sensor_identity(WITHOUT_GPS, 0)
    assert (a0.device_id, a0.external) == (466441, True)
    assert (a1.device_id, a1.external) == (131594, False)
    assert b0.device_id == a1.device_id != a0.device_id
    assert "I2C bus 1, address 0x1e" in a0.describe() and "SPI" in a1.describe()
    assert sensor_identity(WITH_GPS, 2).device_id is None  # an empty slot names no sensor
    assert sensor_identity({}, 0).device_id is None


def test_px4_slots_name_their_sensor() -> None:
    params = {"CAL_MAG0_ID": 396321.0, "CAL_MAG0_ROT": -1.0, "CAL_MAG1_ID": -5.0, "CAL_MAG1_ROT": 0.0}
    s0, s1 = sensor_identity(params, 0), sensor_identity(params, 1)
    assert (s0.device_id, s0.external, s0.source) == (396321, False, "CAL_MAG0_ID")
    assert (s1.device_id, s1.external) == (2**32 - 5, True)  # an int32 parameter holding a uint32 id
    # an id outside the packed bus layout (pyulog's sample log) is named as it is
    assert sensor_identity({"CAL_MAG0_ID": 262144.0}, 0).describe() == "device id 262144"


def test_flights_are_paired_by_sensor_not_by_slot() -> None:
    """Three flights: the slot-0 sensor of the third is the slot-1 sensor of the first two; a fourth flight's
    log names no sensor. Pairs form per sensor, the slot change is said, the unnamed log joins its slot's
    one sensor with a note."""
    entries = [
        ("f1", 0, 466441),
        ("f1", 1, 131594),
        ("f2", 0, 466441),
        ("f2", 1, 131594),
        ("f3", 0, 131594),
        ("f4", 0, None),
    ]
    groups, notes = group_by_sensor(entries)
    assert groups == {"sensor 466441": [0, 2], "sensor 131594": [1, 3, 4], "slot 0": [5]}
    assert any("slot 0 holds different sensors" in n for n in notes)
    groups, notes = group_by_sensor([("f1", 0, 73225), ("f2", 0, 73225), ("f3", 0, None)])
    assert groups == {"sensor 73225": [0, 1, 2]}
    assert any("f3 compass 0: the log does not name its sensor" in n for n in notes)
