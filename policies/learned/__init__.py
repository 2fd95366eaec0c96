"""The learned policies: DDQN and DDPG on stable-baselines3, the CNN, residual actions, and the
checkpoint format they are saved in and loaded from (one UAV or a fleet)."""
