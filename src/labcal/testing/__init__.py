"""Test doubles that speak the real protocols: fake serial trackers on a pty and a fake UR controller (RTDE).

They live here, outside ``labcal.drivers``, because nothing at runtime may use them (an import contract says so);
tests, benchmarks and simulated set-ups import them explicitly:

    from labcal.testing.fakes import FakeNDIDevice
    from labcal.testing.rtde_fake import FakeRTDEServer
"""
