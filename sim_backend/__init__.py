"""The simulated DC servo with friction, and servers that expose it over real protocols."""
