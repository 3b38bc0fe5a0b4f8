"""DAVIS IMU samples in AEDAT 2.0 (jAER) files: address layout, full scales, camera axes.

Facts (jAER ``DavisChip``, ``IMUSample``, ``IMUSampleType``; InvenSense MPU-6150 datasheet):

* an IMU record has bit 31 set and bits 10-11 both set (``addr & 0x80000C00 == 0x80000C00``;
  an APS sample has bit 31 set and bits 10-11 = 0, 1 or 2, its read cycle);
* bits 28-30 hold the sample type: 0 accelerometer x, 1 y, 2 z, 3 temperature, 4 gyro x, 5 y,
  6 z; bits 12-27 the 16-bit two's-complement reading;
* one sample is 7 consecutive records of types 0..6 with one timestamp (jAER writes the
  sample's time on each; evchain takes the first record's);
* scales: the gyro gives 131, 65.5, 32.8, 16.4 LSB per deg/s at a full scale of 250, 500, 1000,
  2000 deg/s, the accelerometer 16384, 8192, 4096, 2048 LSB per g at 2, 4, 8, 16 g; the
  temperature is ``raw / 340 + 35`` °C. jAER's preferences in the header name the full scales
  (``ImuGyroScale`` = ``GyroFullScaleDegPerSec1000``, ``ImuAccelScale`` = ``ImuAccelScaleG8``)
  and the registers written to the chip (``imu3_GYRO_CONFIG``, ``imu4_ACCEL_CONFIG``: full
  scale select in bits 3-4).

Camera axes. evchain's camera frame is x right, y down, z forward (the optical axis), right
handed, as its pixel coordinates (x right, y down). jAER maps the chip's readings to the
camera's as ``accelX = -ax``, ``accelY = ay``, ``tilt = -gx``, ``pan = gy``, ``roll = -gz``
(``IMUSample``), with pan positive when the camera turns right (about +y, down), tilt
positive when it turns up (about +x) and roll positive clockwise seen from behind the camera
(about +z). The chip's frame is right handed like the camera's, so the mapping is a proper
rotation: 180 degrees about y, which also gives ``az_camera = -az`` (jAER leaves the sign of
accelZ unchecked). In the camera frame the series carries:

* ``gx, gy, gz``: angular velocity of the camera in deg/s about its x, y, z axes (right-hand
  rule), i.e. tilt up, pan right, roll clockwise as seen from behind;
* ``ax, ay, az``: specific force in g (what an accelerometer measures: at rest it points up,
  so an upright camera reads ``ay`` near -1);
* ``temperature_c``.

libcaer (and so iniVation's DV and its AEDAT 4.0 ``IMUS`` stream) gives the same chip axes,
already in g and deg/s; the ROS driver of rpg_dvs_ros turns them into the camera frame with
the same signs (x and z negated, "align axes with camera frame") before it publishes
``sensor_msgs/Imu``, so its messages are in evchain's camera axes already (in m/s² and rad/s).
:func:`camera_axes` and :func:`sensor_axes` convert between the two.

On the DVSFLOW16 recording ``IMU_rotDisk`` these conventions agree with the data: the camera
starts upright (``ay`` = -1.01 g), and the gravity direction in the image plane turns with the
sign and rate of ``gz`` (see ``docs/explanation/imu_truth.md``).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from evchain.core.series import IMU
from evchain.errors import DataError

#: jAER's ``DavisChip.ADDRESS_TYPE_IMU``: bit 31 and bits 10-11
IMU_MASK = 0x80000C00
SAMPLE_RECORDS = 7
CODE_SHIFT = 28
DATA_SHIFT = 12

#: LSB per deg/s by gyro full scale (deg/s)
GYRO_LSB_PER_DPS = {250: 131.0, 500: 65.5, 1000: 32.8, 2000: 16.4}
#: LSB per g by accelerometer full scale (g)
ACCEL_LSB_PER_G = {2: 16384.0, 4: 8192.0, 8: 4096.0, 16: 2048.0}
TEMP_LSB_PER_C = 340.0
TEMP_OFFSET_C = 35.0

#: sign of each reading (ax, ay, az, temperature, gx, gy, gz) in evchain's camera axes
CAMERA_SIGNS = np.array([-1.0, 1.0, -1.0, 1.0, -1.0, 1.0, -1.0])


@dataclass(frozen=True)
class ImuScales:
    """Full scales of the gyro (deg/s) and accelerometer (g); None where unknown."""

    gyro_dps: int | None
    accel_g: int | None
    source: str = ""


def scales_from_header(lines: list[str]) -> ImuScales:
    """The full scales jAER's preferences in the header name, None for those it does not.

    ``ImuGyroScale``/``ImuAccelScale`` entries first, else the ``imu3_GYRO_CONFIG`` /
    ``imu4_ACCEL_CONFIG`` registers; a header whose entries and registers disagree is a
    :class:`DataError` (which one the chip ran with is then unknown).
    """
    text = "\n".join(lines)
    named_g = re.search(r'key="[^"]*ImuGyroScale"\s+value="\D*(\d+)"', text)
    named_a = re.search(r'key="[^"]*ImuAccelScale"\s+value="\D*(\d+)"', text)
    reg_g = re.search(r'key="[^"]*GYRO_CONFIG"\s+value="(\d+)"', text)
    reg_a = re.search(r'key="[^"]*ACCEL_CONFIG"\s+value="(\d+)"', text)
    gyro = int(named_g.group(1)) if named_g else None
    accel = int(named_a.group(1)) if named_a else None
    gyro_reg = 250 << ((int(reg_g.group(1)) >> 3) & 3) if reg_g else None
    accel_reg = 2 << ((int(reg_a.group(1)) >> 3) & 3) if reg_a else None
    for what, named, reg, allowed in (("gyro", gyro, gyro_reg, GYRO_LSB_PER_DPS),
                                      ("accelerometer", accel, accel_reg, ACCEL_LSB_PER_G)):
        if named is not None and named not in allowed:
            raise DataError(f"the header names a {what} full scale of {named}, expected one of "
                            f"{', '.join(map(str, allowed))}")
        if named is not None and reg is not None and named != reg:
            raise DataError(f"the header's {what} full scale ({named}) disagrees with the "
                            f"register jAER wrote to the chip ({reg}); set the full scale "
                            "parameter to the one the recording was made with")
    parts = []
    if named_g or named_a:
        parts.append("ImuGyroScale/ImuAccelScale")
    if (gyro is None and gyro_reg is not None) or (accel is None and accel_reg is not None):
        parts.append("GYRO_CONFIG/ACCEL_CONFIG registers")
    return ImuScales(gyro if gyro is not None else gyro_reg,
                     accel if accel is not None else accel_reg,
                     "header " + " and ".join(parts) if parts else "")


def resolve_scales(header: ImuScales, gyro_dps: int | None, accel_g: int | None,
                   where: str) -> ImuScales:
    """The header's full scales, or the parameters' where the header says none; a parameter
    that contradicts the header is a :class:`DataError` naming ``where`` (the file)."""
    for what, given, found, key in (("gyro", gyro_dps, header.gyro_dps, "gyro_full_scale_dps"),
                                    ("accelerometer", accel_g, header.accel_g,
                                     "accel_full_scale_g")):
        if given is not None and found is not None and given != found:
            raise DataError(f"{where}: the parameter {key} is {given} but the header says the "
                            f"{what} full scale is {found}; remove the parameter to use the "
                            "header's")
    return ImuScales(header.gyro_dps if header.gyro_dps is not None else gyro_dps,
                     header.accel_g if header.accel_g is not None else accel_g,
                     header.source or "parameters")


def is_imu(addr: np.ndarray) -> np.ndarray:
    """Which uint32 DAVIS addresses are IMU records."""
    return (addr & np.uint32(IMU_MASK)) == np.uint32(IMU_MASK)


@dataclass
class ImuAssembler:
    """Groups IMU records into samples across chunks and converts them to the camera's axes.

    Feed the IMU records of each chunk in file order (:meth:`add`); complete samples come back
    as :data:`~evchain.core.series.IMU` entries. A sample must be 7 consecutive IMU records of
    types 0..6; records that do not form one (a cut file, a lost record) are dropped and
    counted in ``dropped_records``, the first one's record index in ``first_dropped``.
    """

    scales: ImuScales
    where: str = ""
    samples: int = 0
    dropped_records: int = 0
    first_dropped: int | None = None
    _carry: tuple[np.ndarray, ...] | None = field(default=None, repr=False)

    def add(self, addr: np.ndarray, t: np.ndarray, record: np.ndarray) -> np.ndarray:
        """``addr`` (uint32), ``t`` (int64 µs) and file record index of IMU records, in file
        order. Returns the complete samples as IMU series entries."""
        if len(addr) and (self.scales.gyro_dps is None or self.scales.accel_g is None):
            missing = [k for k, v in (("gyro_full_scale_dps (250, 500, 1000 or 2000 deg/s)",
                                       self.scales.gyro_dps),
                                      ("accel_full_scale_g (2, 4, 8 or 16 g)",
                                       self.scales.accel_g)) if v is None]
            raise DataError(f"{self.where}: record {int(record[0])} is an IMU sample, but the "
                            "header does not say the IMU's full scale (no jAER ImuGyroScale/"
                            "ImuAccelScale entries or GYRO_CONFIG/ACCEL_CONFIG registers); "
                            f"set {' and '.join(missing)} as the recording was made, or "
                            "imu: false to skip the IMU records")
        if self._carry is not None:
            addr, t, record = (np.concatenate([c, a]) for c, a in
                               zip(self._carry, (addr, t, record), strict=True))
            self._carry = None
        n = len(addr)
        if n == 0:
            return np.zeros(0, IMU.dtype)
        code = ((addr >> np.uint32(CODE_SHIFT)) & np.uint32(7)).astype(np.int64)
        starts = np.flatnonzero(code == 0)
        full = starts[starts + SAMPLE_RECORDS <= n]
        window = full[:, None] + np.arange(SAMPLE_RECORDS)
        ok = np.all(code[window] == np.arange(SAMPLE_RECORDS), axis=1)
        good = full[ok]
        used = np.zeros(n, bool)
        used[(good[:, None] + np.arange(SAMPLE_RECORDS)).ravel()] = True
        # a started sample at the end of the chunk may complete in the next one
        tail = n
        if len(starts) and starts[-1] + SAMPLE_RECORDS > n:
            s = int(starts[-1])
            if np.array_equal(code[s:], np.arange(n - s)):
                tail = s
        if tail < n:
            self._carry = (addr[tail:], t[tail:], record[tail:])
        lost = ~used[:tail]
        self._drop(record[:tail][lost])
        raw = ((addr[(good[:, None] + np.arange(SAMPLE_RECORDS))] >> np.uint32(DATA_SHIFT))
               & np.uint32(0xFFFF)).astype(np.uint16).view(np.int16).astype(np.float64)
        self.samples += len(good)
        return self.entries(t[good], raw)

    def finish(self) -> None:
        """End of the file: a started sample that never completed is dropped."""
        if self._carry is not None:
            self._drop(self._carry[2])
            self._carry = None

    def _drop(self, records: np.ndarray) -> None:
        if len(records):
            self.dropped_records += len(records)
            if self.first_dropped is None:
                self.first_dropped = int(records[0])

    def entries(self, t: np.ndarray, raw: np.ndarray) -> np.ndarray:
        """Series entries from times and raw readings ``[n, 7]`` (types 0..6)."""
        v = raw * CAMERA_SIGNS
        a = 1.0 / ACCEL_LSB_PER_G[self.scales.accel_g]
        g = 1.0 / GYRO_LSB_PER_DPS[self.scales.gyro_dps]
        return IMU.array(t=t, ax=v[:, 0] * a, ay=v[:, 1] * a, az=v[:, 2] * a,
                         gx=v[:, 4] * g, gy=v[:, 5] * g, gz=v[:, 6] * g,
                         temperature_c=v[:, 3] / TEMP_LSB_PER_C + TEMP_OFFSET_C)


def encode_samples(t: np.ndarray, raw: np.ndarray) -> np.ndarray:
    """Records ``[7 n, 2]`` (uint32 address, timestamp) of IMU samples with raw readings
    ``raw`` (int16 ``[n, 7]``, types 0..6): the layout jAER writes. For tests and writers."""
    raw = np.asarray(raw, np.int64)
    n = len(t)
    codes = np.broadcast_to(np.arange(SAMPLE_RECORDS, dtype=np.uint32), (n, SAMPLE_RECORDS))
    data = (raw.astype(np.uint32) & np.uint32(0xFFFF)) << np.uint32(DATA_SHIFT)
    addr = np.uint32(IMU_MASK) | (codes << np.uint32(CODE_SHIFT)) | data
    out = np.empty((n * SAMPLE_RECORDS, 2), np.uint32)
    out[:, 0] = addr.ravel()
    out[:, 1] = np.repeat(np.asarray(t, np.int64) & 0xFFFFFFFF, SAMPLE_RECORDS).astype(np.uint32)
    return out


def camera_axes(t, accel_g, gyro_dps, temperature_c) -> np.ndarray:
    """IMU series entries (camera axes) from a DAVIS IMU's readings in its chip's axes, as
    libcaer and DV give them: ``accel_g`` and ``gyro_dps`` ``[n, 3]`` (x, y, z)."""
    a = np.asarray(accel_g, np.float64).reshape(-1, 3) * CAMERA_SIGNS[0:3]
    g = np.asarray(gyro_dps, np.float64).reshape(-1, 3) * CAMERA_SIGNS[4:7]
    return IMU.array(t=t, ax=a[:, 0], ay=a[:, 1], az=a[:, 2], gx=g[:, 0], gy=g[:, 1],
                     gz=g[:, 2], temperature_c=temperature_c)


def sensor_axes(entries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(accel_g, gyro_dps)`` ``[n, 3]`` in a DAVIS IMU's chip axes from IMU series entries:
    the inverse of :func:`camera_axes`."""
    a = np.stack([entries["ax"], entries["ay"], entries["az"]], 1) * CAMERA_SIGNS[0:3]
    g = np.stack([entries["gx"], entries["gy"], entries["gz"]], 1) * CAMERA_SIGNS[4:7]
    return a, g
