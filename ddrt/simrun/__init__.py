"""`ddrt sim`: the closed loop on the simulated robot as fast as the CPU allows, its tracking
metrics and its figures."""
