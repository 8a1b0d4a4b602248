"""labcal-fakes: test doubles for labcal that speak the real protocols, shipped beside labcal, not in it.

A fake NDI tracker (and any line device) on a pseudo-terminal, a fake UR controller serving RTDE, dashboard and
script ports in its own process, and the rehearsal rig that runs both on one simulated robot. labcal never
imports this package (an import contract says so); labcal's tests, its benchmarks and a rehearsal before a lab
day import it explicitly:

    from labcal_fakes.devices import FakeNDIDevice
    from labcal_fakes.rtde_fake import FakeRTDEServer
    python -m labcal_fakes.rehearse --targets drivers/targets-example.toml
"""
