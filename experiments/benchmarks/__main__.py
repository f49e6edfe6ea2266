"""``python -m experiments.benchmarks``: the suite of :mod:`experiments.benchmarks.suite`."""

from experiments.benchmarks.suite import main

if __name__ == "__main__":
    main()
