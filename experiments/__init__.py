"""Everything that runs the method on the simulated Panda: the closed-loop runner, the demos of `python sim.py`,
the paper's tables, benchmarks and timings, and the network's training data."""
