"""What more than one test module needs, imported as `from tests.support.<module> import ...`
(no test imports another test module or bench/):

- repo: the repository's root and configs/sim.yaml;
- daemon: the real `ddrt run` process, driven from outside (socket, signals, `ddrt ctl`);
- drive_rigs, reload_rig: a loop or a daemon's parts in process, in simulated time;
- following: a loop on a backend following its config's path, ticked in the backend's time;
- firmware: build the reference firmware and its simavr harness, or skip;
- fuzz_inputs: seeded mutations of every file in configs/, fed to `ddrt sim`;
- path_inputs, cusp_inputs, reverse_paths: paths as people hand them over (bench/ runs
  path_inputs and cusp_inputs too);
- seed_robot: the seed report's Table 5.1 and 5.2 robots.
"""
