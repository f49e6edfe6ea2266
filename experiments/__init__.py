"""The experiments, run from a checkout (not installed): ``python -m experiments.<package>.<name>``.

* ``paper``: the paper's experiments reproduced (texture, volume, meshes, pytrees, figures);
* ``mitsuba``: the optimizers in Mitsuba 3's own loops and scenes;
* ``tuning``: the tuning benchmark (``python -m experiments.tuning``) and its scenes;
* ``benchmarks``: speed, memory and compile time (``python -m experiments.benchmarks``);
* ``common``: what they share (runs, timing, summaries, plots).

``tools/`` may import these; nothing here imports ``tools/``.
"""
