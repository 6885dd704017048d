"""What more than one test module needs, imported as `from tests.support.<module> import ...`
(no test imports another test module, and only bench's own tests, test_bench_*.py, import
bench/):

- repo: the repository's root and configs/sim.yaml;
- daemon: the real `ddrt run` process, driven from outside (socket, signals, `ddrt ctl`);
- drive_rigs, reload_rig: a loop or a daemon's parts in process, in simulated time;
- following: a loop on a backend following its config's path, ticked in the backend's time;
- firmware: build the reference firmware and its simavr harness, or skip;
- fuzz_inputs: seeded mutations of every file in configs/, fed to `ddrt sim`;
- reverse_paths: reversing paths as people write them, as files (the paths as people hand
  them over that bench/ runs too are in lab/, which tests import as bench does);
- seed_robot: the seed report's Table 5.1 and 5.2 robots.
"""
