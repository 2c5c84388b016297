"""The pybullet twin: scenes, the simulated Panda and D435. Never imports planners/."""
