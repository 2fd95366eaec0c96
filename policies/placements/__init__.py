"""Placements that are not learned: the baselines, the oracles and the planner, for one UAV and
for a fleet (users' positions and loads in, positions out)."""
