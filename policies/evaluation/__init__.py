"""Evaluation: ``tupa eval``, one episode per scenario, for one UAV or a fleet."""
