"""The simulated can world and the robot's throw: the physics the experiments' data come from."""
