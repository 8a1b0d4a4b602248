"""Serial tracker driver internals: checksums, link/framer, profiles, NDI and ASCII protocols, matching.

Use the public names from ``labcal.drivers.serial_tracker``.
"""
