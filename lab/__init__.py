"""What the tests and the benchmarks both run, so neither imports the other: tests/ checks the
product, bench/ measures it, and the inputs both hold to the same targets live here.

- repo: the repository's root and configs/sim.yaml;
- path_inputs, cusp_inputs: paths as people hand them over (recordings, planner output,
  manoeuvres with cusps), generated with fixed seeds, with the targets they are held to;
- soak: a soak's growth per command cycle and its verdict (bench/soak.py samples the daemon).

Not part of the installed package (pyproject.toml ships ddrt, hal and sim_hal only): it is
used from a checkout, as tests/ and bench/ are.
"""
