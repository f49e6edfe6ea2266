"""The README's code runs and prints what the README says it prints."""

import math
import pathlib
import re
import subprocess
import sys

import jax
import jax.numpy as jnp
import optax

ROOT = pathlib.Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
# XLA may order a float32 sum differently across versions and machines: the last printed
# digit (1e-4) may move by a few units, more would be a different result.
PRINT_TOLERANCE = 5e-4


def quickstart() -> tuple[str, str]:
    """(the quick start's Python block, the output block the README shows for it)."""
    start, end = "<!-- --8<-- [start:quickstart] -->", "<!-- --8<-- [end:quickstart] -->"
    section = README.split(start, 1)[1].split(end, 1)[0]
    code = re.search(r"```python\n(.*?)```", section, re.S).group(1)
    shown = re.search(r"```text\n(.*?)```", section, re.S).group(1)
    return code, shown


def numbers(text: str) -> dict[str, float]:
    """``name value`` lines as a dict."""
    return {
        line.rsplit(None, 1)[0]: float(line.rsplit(None, 1)[1])
        for line in text.strip().splitlines()
    }


def test_readme_is_short_and_the_quickstart_fits_in_20_lines():
    code, _ = quickstart()
    assert len(README.splitlines()) <= 150
    assert len([line for line in code.splitlines() if line.strip()]) <= 20
    assert "ob.bilateral_adam(learning_rate=" in code and "jax.jit" in code and "jax.grad" in code


def test_quickstart_lowers_the_error_and_prints_what_the_readme_shows():
    code, shown = quickstart()
    run = subprocess.run(
        [sys.executable, "-c", code],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
        check=True,
    )
    printed = numbers(run.stdout)
    expected = numbers(shown)
    assert printed.keys() == expected.keys()
    assert all(math.isfinite(v) for v in printed.values())
    assert printed["ob.bilateral_adam"] < printed["initial error"]
    assert printed["optax.adam"] < printed["initial error"]
    for name, value in expected.items():
        assert abs(printed[name] - value) <= PRINT_TOLERANCE, (name, printed[name], value)


def test_the_three_compositions_run_one_finite_step():
    block = README.split("## The three compositions", 1)[1]
    code = re.search(r"```python\n(.*?)```", block, re.S).group(1)
    namespace: dict = {}
    exec(compile(code, "README.md", "exec"), namespace)
    params = {"tex": jnp.linspace(0.1, 0.9, 16 * 16 * 3).reshape(16, 16, 3)}
    grads = jax.tree.map(lambda p: jax.random.normal(jax.random.key(0), p.shape), params)
    for name in ("pre", "post", "both", "opt"):
        opt = namespace[name]
        updates, _ = opt.update(grads, opt.init(params), params)
        new = optax.apply_updates(params, updates)
        assert bool(jnp.all(jnp.isfinite(new["tex"]))), name
        assert float(jnp.abs(updates["tex"]).max()) > 0, name
