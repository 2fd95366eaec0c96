"""Offline training: ``tupa train`` for one UAV or a fleet, its hyper-parameter presets, the
vectorised environment, imitation of the fleet oracle and a long run's progress."""
