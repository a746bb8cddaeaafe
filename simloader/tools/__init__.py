"""Tools around the runtime package, imported only by the commands that use them: `bench.py`,
simloader next to the raw simulators it wraps (`simloader bench`, benchmarks/)."""
