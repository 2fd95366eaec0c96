"""The ns-3 calibration set: cases (``cases.json``), their ns-3 3.44 results (``ns3_*.json``)
and the script that builds both (:mod:`sim.calibration.build`)."""
