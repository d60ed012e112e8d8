"""Benchmarks and experiment harnesses, in one home.

eg-bench (methods x scenes x seeds through the normal trainer, the paper's tables and plots)::

    from exploregs_plugin.bench.presets import preset
    from exploregs_plugin.bench.report import run_bench
    payload = run_bench(preset("quick"), Path("bench-quick"))

and the component benchmarks, each a script that prints a table: ``python -m
exploregs_plugin.bench.rasterizer`` (speed, memory and error of the rasterizer), ``python -m
exploregs_plugin.bench.train_step`` (a training step against the bare renderer step), ``python -m
exploregs_plugin.bench.opcost`` (per-element cost of torch ops) and ``python -m
exploregs_plugin.bench.viewer`` (training speed with the live viewer). Nothing is imported here,
so a component benchmark does not load the trainer.
"""
