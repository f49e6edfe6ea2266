"""The learning rates of the README's quick start: a sweep on its own problem.

    python -m experiments.quickstart_sweep

Runs the quick start's ``run`` (read from README.md, so the problem is the one the README
shows) for ``ob.bilateral_adam`` and ``optax.adam`` at learning rates 0.0025 * 2**k,
k = 0..7, and prints the final mean absolute error of each; the README uses each
optimizer's best.
"""

import pathlib
import re

import optax

import optax_bilateral as ob

README = pathlib.Path(__file__).resolve().parents[1] / "README.md"
LEARNING_RATES = tuple(0.0025 * 2**k for k in range(8))


def quickstart_source(readme: pathlib.Path = README) -> str:
    """The Python block between the README's quick-start markers."""
    text = readme.read_text()
    start, end = "<!-- --8<-- [start:quickstart] -->", "<!-- --8<-- [end:quickstart] -->"
    section = text.split(start, 1)[1].split(end, 1)[0]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def main() -> dict:
    namespace: dict = {}
    lines = quickstart_source().splitlines()
    setup = "\n".join(line for line in lines if not line.startswith("print("))
    exec(compile(setup, str(README), "exec"), namespace)
    errors = {}
    for name, make in (("ob.bilateral_adam", ob.bilateral_adam), ("optax.adam", optax.adam)):
        errors[name] = {lr: namespace["run"](make(learning_rate=lr)) for lr in LEARNING_RATES}
        for lr, err in errors[name].items():
            print(f"{name:18s} learning_rate {lr:<7g} error {err:.4f}")
        best = min(errors[name], key=errors[name].get)
        print(f"{name:18s} best: learning_rate {best:g}, error {errors[name][best]:.4f}")
    return errors


if __name__ == "__main__":
    main()
