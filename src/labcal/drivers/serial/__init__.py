"""Serial tracker driver (1..m targets): pyserial transport -> framer (``link``) -> protocol profile (``profiles``:
the ``ascii`` line protocol or the NDI Combined API, ``ndi``) -> the ``Tracker`` port (``tracker.SerialTracker``,
``tracker.open_tracker``); ``matching`` labels unordered markers, ``crc`` holds the checksums.
"""
