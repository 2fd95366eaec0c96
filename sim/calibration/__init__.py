"""The ns-3 calibration set: cases (``cases.json``), their ns-3 3.44 results (``ns3_*.json``),
the script that builds both (:mod:`sim.calibration.build`), and the fit of the fast model's free
constants to its fit part (:mod:`sim.calibration.fit` → ``fitted.json``)."""
