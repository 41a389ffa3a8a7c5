"""Which physical sensor a compass index of a log is, from the log's own parameters.

A compass index is the autopilot's slot, not a sensor: when a GPS module with its compass is unplugged, the
board's internal compass moves up to slot 0 (measured: yladzislay's Pixhawk 1, sample-3 logs its internal
LSM303D as compass 0, the other two logs as compass 1). Comparing theta between two flights by index then
compares two sensors. Both autopilots name the sensor in each slot by its device id (bus type, bus, address
and driver type packed in one integer, the same layout in ArduPilot's ``AP_HAL::Device`` and PX4's
``device::Device``):

- ArduPilot: ``COMPASS_DEV_ID`` (slot 0), ``COMPASS_DEV_ID2``, ``COMPASS_DEV_ID3``, ...; external flags
  ``COMPASS_EXTERNAL``, ``COMPASS_EXTERN2``, ``COMPASS_EXTERN3``;
- PX4: ``CAL_MAGn_ID`` of slot n (the ulog reader puts a ``sensor_mag`` instance in the slot whose
  ``CAL_MAGn_ID`` is its ``device_id``); external when ``CAL_MAGn_ROT`` >= 0 (an internal compass has -1).
  A sensor the autopilot has not calibrated keeps its instance number as slot, and that slot's
  ``CAL_MAGn_ID`` may then name another sensor: the log's ``device_id`` is not carried into
  :class:`~magcomp.core.types.LogData`, so this case is not told apart here.

A device id names where a sensor sits and which driver reads it, not a serial number: two Pixhawks with a
3DR GPS share 73225 (HMC5883 on I2C) and 131594 (the board's LSM303D), so it tells sensors apart within one
vehicle only. A telemetry log carries the ids only when the ground station fetched the parameters. Pure, no
I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

from magcomp.core.autopilot_params import external_compass

#: device-id bus types (bits 0-2), as both autopilots number them
BUS_TYPES = {1: "I2C", 2: "SPI", 3: "UAVCAN", 4: "simulated", 5: "MSP", 6: "serial"}


@dataclass(frozen=True)
class SensorIdentity:
    """The sensor in a compass slot: device id (None: the log does not say), external flag (None: not said),
    and the parameter it was read from."""

    device_id: int | None
    external: bool | None
    source: str

    @property
    def key(self) -> str | None:
        """What two flights' compasses must share to be the same sensor (None: unknown)."""
        return None if self.device_id is None else str(self.device_id)

    def describe(self) -> str:
        """One phrase: ``device id 466441 (I2C bus 1, address 0x1e), external``."""
        if self.device_id is None:
            return "sensor not named in the log"
        d = self.device_id
        bus = BUS_TYPES.get(d & 0x7)
        text = f"device id {d}"
        if bus is not None:  # the packed layout (older PX4 ids, e.g. 262144, use another one)
            text += f" ({bus} bus {(d >> 3) & 0x1F}, address 0x{(d >> 8) & 0xFF:02x})"
        if self.external is not None:
            text += ", external" if self.external else ", internal"
        return text


def _ardupilot_id_param(index: int) -> str:
    return "COMPASS_DEV_ID" if index == 0 else f"COMPASS_DEV_ID{index + 1}"


def sensor_identity(params: dict[str, float], index: int) -> SensorIdentity:
    """The sensor in compass slot ``index`` (module docstring); a device id of 0 means the slot is empty in
    the autopilot's table, so the log does not name the sensor it logged there."""
    name = _ardupilot_id_param(index)
    ap = params.get(name)
    if ap is not None:
        return SensorIdentity(_device_id(ap), external_compass(params, index), name)
    name = f"CAL_MAG{index}_ID"
    px4 = params.get(name)
    if px4 is not None:
        rot = params.get(f"CAL_MAG{index}_ROT")
        return SensorIdentity(_device_id(px4), None if rot is None else rot >= 0, name)
    return SensorIdentity(None, external_compass(params, index), "")


def _device_id(value: float) -> int | None:
    """A device id parameter (an int32 holding a uint32) as the unsigned id; None for 0 (no sensor)."""
    dev = int(value) & 0xFFFFFFFF
    return dev if dev > 0 else None


def group_by_sensor(entries: list[tuple[str, int, int | None]]) -> tuple[dict[str, list[int]], list[str]]:
    """Group compasses of several flights of one vehicle by the sensor they are.

    ``entries``: per compass (flight name, slot index, device id or None). Returns groups (``"sensor ID"`` or,
    where no flight names the sensor in that slot, ``"slot N"``) of positions in ``entries``, and one line per
    decision the grouping made that a reader should know of: a slot that holds different sensors in different
    flights (those are not paired: a pair of two sensors is not a repeat), and a compass whose flight does not
    name its sensor, paired by slot with the one sensor the vehicle's other flights have there (an
    assumption: said, not hidden)."""
    groups: dict[str, list[int]] = {}
    notes: list[str] = []
    slot_ids: dict[int, list[tuple[str, int]]] = {}
    for name, slot, dev in entries:
        if dev is not None:
            slot_ids.setdefault(slot, []).append((name, dev))
    for slot, named in sorted(slot_ids.items()):
        if len({dev for _, dev in named}) > 1:
            who = ", ".join(f"{name}: {dev}" for name, dev in named)
            notes.append(
                f"compass slot {slot} holds different sensors in different flights ({who}): paired by device "
                "id, not by slot (a pair of two sensors is not a repeat and is not compared)"
            )
    for pos, (name, slot, dev) in enumerate(entries):
        if dev is None:
            ids = {d for _, d in slot_ids.get(slot, [])}
            if len(ids) == 1:
                dev = next(iter(ids))
                notes.append(
                    f"{name} compass {slot}: the log does not name its sensor; paired by slot with sensor "
                    f"{dev} (the one the vehicle's other flights have in that slot)"
                )
        groups.setdefault(f"slot {slot}" if dev is None else f"sensor {dev}", []).append(pos)
    return groups, notes
