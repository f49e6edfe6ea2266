"""The README's code runs and prints what the README says it prints."""

import math
import os
import pathlib
import subprocess
import sys

import jax
import jax.numpy as jnp
import optax

import docs_blocks

ROOT = pathlib.Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()


def quickstart() -> tuple[str, str]:
    """(the quick start's Python block, the output block the README shows for it)."""
    block = docs_blocks.by("README.md", "quickstart")
    return block.code, block.prints


def numbers(text: str) -> dict[str, float]:
    """``name value`` lines as a dict."""
    return {
        line.rsplit(None, 1)[0]: float(line.rsplit(None, 1)[1])
        for line in text.strip().splitlines()
    }


def test_readme_is_short_and_the_quickstart_fits_in_20_lines():
    code, _ = quickstart()
    # What a reader sees: the comments that mark blocks for the tests are not shown.
    assert len([line for line in README.splitlines() if not line.startswith("<!--")]) <= 150
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
        env={**os.environ, "JAX_LOG_COMPILES": "1"},
    )
    # Its jitted step compiles once per optimizer: the state keeps its types (no weak type
    # lost after the first update), so the second call finds the first one's program.
    assert run.stderr.count("Compiling jit(step)") == 2, run.stderr[-3000:]
    printed = numbers(run.stdout)
    expected = numbers(shown)
    assert printed.keys() == expected.keys()
    assert all(math.isfinite(v) for v in printed.values())
    assert printed["ob.bilateral_adam"] < printed["initial error"]
    assert printed["optax.adam"] < printed["initial error"]
    assert docs_blocks.compare_prints(run.stdout, shown) == []


def test_the_three_compositions_run_one_finite_step():
    code = docs_blocks.by("README.md", "compositions").code
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
