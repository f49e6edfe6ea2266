"""``python -m experiments.tuning``: the tuning benchmark's command line."""

from experiments.tuning import main

if __name__ == "__main__":
    main()
