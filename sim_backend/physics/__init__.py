"""The simulated plant: the DC servo with friction, its effects and integrators."""
