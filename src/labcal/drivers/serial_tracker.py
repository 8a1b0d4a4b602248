"""Serial tracker driver (1..m targets): pyserial transport -> framer -> protocol profile -> ``Tracker`` port.

Profiles (TOML, see the repository's ``drivers/`` folder, or the built-in ``ascii-single-smr``): a configurable
ASCII line protocol and the NDI Combined API (Polaris passive stray markers, ASCII ``TX`` or binary ``BX``
replies). Everything is in SI units (m, s) once it leaves this driver; targets a frame did not see are NaN rows.

    with open_tracker("drivers/ndi-polaris.toml", targets, url="/dev/ttyUSB0") as tracker:
        m = tracker.measure(samples=5)
"""

from labcal.drivers.serial.crc import crc16_arc
from labcal.drivers.serial.link import SerialLink, Transport, open_serial
from labcal.drivers.serial.matching import check_scalene, match_targets
from labcal.drivers.serial.ndi import (
    ERROR_CODES,
    NDIError,
    StrayFrame,
    decode_reply,
    encode_command,
    parse_bx_strays,
    parse_tx_strays,
)
from labcal.drivers.serial.profiles import (
    AsciiProfile,
    NDIProfile,
    PortSettings,
    Profile,
    ProfileError,
    load_profile,
    parse_profile,
)
from labcal.drivers.serial.tracker import SerialTracker, open_tracker

__all__ = [
    "ERROR_CODES",
    "AsciiProfile",
    "NDIError",
    "NDIProfile",
    "PortSettings",
    "Profile",
    "ProfileError",
    "SerialLink",
    "SerialTracker",
    "StrayFrame",
    "Transport",
    "check_scalene",
    "crc16_arc",
    "decode_reply",
    "encode_command",
    "load_profile",
    "match_targets",
    "open_serial",
    "open_tracker",
    "parse_bx_strays",
    "parse_profile",
    "parse_tx_strays",
]
